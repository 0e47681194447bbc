"""Per-kernel trace summaries (heisd_jax.timing, behind experiments/trace_decode.py): a traced
jitted call shows up on a device timeline, with its time split per call."""

import jax
import jax.numpy as jnp

from heisd_jax import timing


def test_kernel_summary_of_a_traced_call(tmp_path):
    f = jax.jit(lambda x: jnp.tanh(x @ x.T).sum(0))
    x = jnp.ones((384, 384), jnp.float32)
    jax.block_until_ready(f(x))  # compiled before the trace
    one = timing.kernel_summary(timing.trace_calls(lambda: f(x), 1, tmp_path / "one"), calls=1, top=5)
    three = timing.kernel_summary(timing.trace_calls(lambda: f(x), 3, tmp_path / "three"), calls=3, top=5)
    for summary in (one, three):
        assert summary, "no device timeline in the trace"
        for line in summary.values():
            assert line["total_ms"] >= 0 and len(line["top"]) <= 5
            assert [ms for _, ms in line["top"]] == sorted((ms for _, ms in line["top"]), reverse=True)
    # Per-call figures: three calls summarised per call are of the size of one call, not 3x.
    total = lambda s: sum(line["total_ms"] for line in s.values())  # noqa: E731
    assert 0 < total(three) < 2.5 * total(one) + 1.0
