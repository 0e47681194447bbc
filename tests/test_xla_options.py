"""heisd_jax.xla_options: the per-program XLA options are ones the installed jaxlib knows, and
a program compiled with them computes what it computes without."""

import jax
import jax.numpy as jnp
import pytest

from heisd_jax import xla_options


def test_device_loops_is_a_valid_per_program_option():
    """`xla_options.DEVICE_LOOPS` names command-buffer kinds this jaxlib's XLA knows (a renamed
    kind fails the compile), and a program compiled with it computes what it computes without."""
    def rounds(x):  # a while loop and a conditional, as the decode step's rounds and budget
        x = jax.lax.while_loop(lambda c: c[0] < 3, lambda c: (c[0] + 1, c[1] * 2 + 1), (0, x))[1]
        return jax.lax.cond(x.sum() > 0, lambda v: v - 1, lambda v: v + 1, x)

    x = jnp.arange(3.0)
    assert (jax.jit(rounds, compiler_options=xla_options.DEVICE_LOOPS)(x) == jax.jit(rounds)(x)).all()
    with pytest.raises(Exception, match="not a valid enum value"):  # what a stale kind would raise
        jax.jit(rounds, compiler_options={"xla_gpu_enable_command_buffer": "NOT_A_KIND"})(x)


def test_deterministic_is_a_valid_per_program_option():
    """`xla_options.determinism(True)` (training steps' default) is an option this jaxlib's XLA knows,
    and a scatter-add (an embedding's gradient) compiled with it sums what it sums without."""
    def scatter(x, idx):
        return x.at[idx].add(1.0)

    x, idx = jnp.zeros(4), jnp.array([0, 0, 3, 1, 0])
    want = jax.jit(scatter)(x, idx)
    assert (jax.jit(scatter, compiler_options=xla_options.determinism(True))(x, idx) == want).all()
    assert want.tolist() == [3.0, 1.0, 0.0, 1.0]


def test_parse_types_values_and_check_refuses_what_xla_does_not_know():
    """A bool option given as text is refused by XLA, so `parse` types true/false and numbers;
    `check` passes what XLA takes and names what it refuses."""
    opts = xla_options.parse("xla_gpu_deterministic_ops=true, xla_gpu_graph_min_graph_size=3,xla_gpu_enable_command_buffer=")
    assert opts == {"xla_gpu_deterministic_ops": True, "xla_gpu_graph_min_graph_size": 3,
                    "xla_gpu_enable_command_buffer": ""}
    xla_options.check({**xla_options.DEVICE_LOOPS, **opts})
    with pytest.raises(ValueError, match="not a valid bool"):
        xla_options.check({"xla_gpu_deterministic_ops": "true"})
    with pytest.raises(ValueError, match="No such compile option: 'xla_no_such'"):
        xla_options.check({"xla_no_such": 1})
    with pytest.raises(ValueError, match="not key=value"):
        xla_options.parse("xla_gpu_deterministic_ops")
