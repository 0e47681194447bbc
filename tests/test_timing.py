"""Per-kernel trace summaries (heisd_jax.timing, behind experiments/studies/trace_decode.py): a traced
jitted call shows up on a device timeline, with its time split per call."""

import gzip
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import timing


def test_kernel_summary_of_a_traced_call(tmp_path):
    f = jax.jit(lambda x: jnp.tanh(x @ x.T).sum(0))
    x = jnp.ones((384, 384), jnp.float32)
    jax.block_until_ready(f(x))  # compiled before the trace
    path = timing.trace_calls(lambda: f(x), 3, tmp_path / "three")
    assert path is not None and path.name == "perfetto_trace.json.gz", "the profiler wrote no Perfetto trace"
    whole = timing.kernel_summary(path, calls=1, top=5)
    per_call = timing.kernel_summary(path, calls=3, top=5)
    assert whole, "no device timeline in the trace"
    for line in whole.values():
        assert line["total_ms"] > 0 and 1 <= len(line["top"]) <= 5
        assert [ms for _, ms in line["top"]] == sorted((ms for _, ms in line["top"]), reverse=True)
    # Per-call figures: the same events, each divided by the number of calls.
    assert per_call.keys() == whole.keys()
    for name, line in whole.items():
        assert per_call[name]["total_ms"] == pytest.approx(line["total_ms"] / 3)
        assert line["count"] >= len(line["top"]) and per_call[name]["count"] == pytest.approx(line["count"] / 3)
        assert [k for k, _ in per_call[name]["top"]] == [k for k, _ in line["top"]]
        np.testing.assert_allclose([ms for _, ms in per_call[name]["top"]], [ms / 3 for _, ms in line["top"]])


def test_write_hlo_keeps_the_optimised_program_that_names_the_kernels(tmp_path):
    f = jax.jit(lambda x: jnp.tanh(x @ x.T).sum(0))
    x = jnp.ones((64, 64), jnp.float32)
    path = timing.write_hlo(f, (x,), tmp_path / "sub" / "f.hlo.txt.gz")
    with gzip.open(path, "rt") as fh:
        text = fh.read()
    assert text.startswith("HloModule") and "tanh" in text
    assert text == f.lower(x).compile().as_text()  # the compiled program, not the unoptimised one


def test_in_graph_returns_the_pieces_output_from_its_timed_loop():
    def piece(w, x):
        return {"y": jnp.tanh(x @ w), "n": jnp.sum(x > 0)}
    w, x = jnp.eye(16) * 0.5, jnp.arange(32.0).reshape(2, 16) - 8
    ms, out = timing.in_graph(piece, (w, x), n=(1, 3), reps=2)
    assert ms >= 0
    ref = jax.jit(piece)(w, x)
    np.testing.assert_allclose(np.asarray(out["y"]), np.asarray(ref["y"]), rtol=1e-6)
    assert int(out["n"]) == int(ref["n"])
    with pytest.raises(ValueError, match="1 <= n\\[0\\] < n\\[1\\]"):
        timing.in_graph_ms(piece, (w, x), n=(0, 3))


def test_device_gaps_name_what_the_device_waited_for(tmp_path):
    """A synthetic trace: kernels at 0-1 ms and 6-7 ms and 7.2-8 ms on a GPU stream, a host
    call spanning all of it and, inside, a 4.9 ms graph launch over the first idle stretch."""
    meta = [{"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
            {"ph": "M", "name": "thread_name", "pid": 1, "tid": 7, "args": {"name": "Stream #7"}},
            {"ph": "M", "name": "process_name", "pid": 2, "args": {"name": "/host:CPU"}},
            {"ph": "M", "name": "thread_name", "pid": 2, "tid": 3, "args": {"name": "python"}}]
    x = lambda pid, tid, name, ts, dur: {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": ts, "dur": dur}  # noqa: E731
    events = meta + [x(1, 7, "conv", 0, 1000), x(1, 7, "gemm", 6000, 1000), x(1, 7, "tail", 7200, 800),
                     x(2, 3, "jit_act", 0, 9000), x(2, 3, "cuGraphLaunch (CudaGraph:17)", 1100, 4900)]
    path = tmp_path / "t.json.gz"
    with gzip.open(path, "wt") as f:
        json.dump({"traceEvents": events}, f)
    gaps = timing.device_gaps(path, min_ms=0.1)
    assert list(gaps) == ["/device:GPU:0 | Stream #7"]
    first, second = gaps["/device:GPU:0 | Stream #7"]
    assert first == {"start_ms": 1.0, "ms": 5.0, "after": "conv", "before": "gemm",
                     "host": "cuGraphLaunch (CudaGraph:17)", "host_ms": 4.9}
    assert second["ms"] == pytest.approx(0.2) and second["host"] == "jit_act"  # only the call covers it
    assert timing.device_gaps(path, min_ms=1.0)["/device:GPU:0 | Stream #7"] == [first]
    summary = timing.kernel_summary(path, calls=1, top=3)["/device:GPU:0 | Stream #7"]
    assert summary["total_ms"] == pytest.approx(2.8)
    assert summary["launches"] == {"conv": 1, "gemm": 1, "tail": 1}
    with gzip.open(path, "wt") as f:  # the stream's kernels twice over, as in two calls
        json.dump({"traceEvents": events + [dict(e, ts=e["ts"] + 10_000) for e in events[4:7]]}, f)
    summary = timing.kernel_summary(path, calls=2, top=1)["/device:GPU:0 | Stream #7"]
    assert summary["top"] == [("conv", pytest.approx(1.0))] and summary["launches"] == {"conv": 1.0}
