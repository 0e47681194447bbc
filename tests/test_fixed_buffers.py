"""FixedBufferStep: the same results as the plain step, on buffers that do not move."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax.fixed_buffers import FixedBufferStep


def step(params, inputs, carry):
    """A step with a loop and a branch, as the decode step has: results depend on the inputs,
    the carried state and the params; the carry accumulates."""
    obs, key = inputs
    h = jax.lax.fori_loop(0, 3, lambda i, h: jnp.tanh(h @ params["w"] + obs), carry["h"])
    out = jax.lax.cond(key[0] > 0, lambda: h * 2.0, lambda: h - 1.0)
    return {"action": out.sum(-1), "h": out}, {"h": h, "n": carry["n"] + 1}


def _example(seed):
    k = jax.random.split(jax.random.key(seed), 2)
    return jax.random.normal(k[0], (2, 4)), jax.random.randint(k[1], (2,), -1, 2)


def test_equals_the_plain_step_and_keeps_every_buffer_where_it_is():
    params = {"w": 0.5 * jax.random.normal(jax.random.key(9), (4, 4))}
    carry = {"h": jnp.zeros((2, 4)), "n": jnp.zeros((), jnp.int32)}
    fixed = FixedBufferStep(step, params, _example(0), carry)
    addresses = fixed.buffer_addresses()
    plain = jax.jit(step)
    for seed in range(4):
        inputs = _example(seed)
        want, carry = plain(params, inputs, carry)
        got = fixed(inputs)
        jax.tree.map(np.testing.assert_array_equal, got, want)
        jax.tree.map(np.testing.assert_array_equal, fixed.carry, carry)
        assert fixed.buffer_addresses() == addresses
    assert int(fixed.carry["n"]) == 4


def test_inputs_of_another_structure_or_shape_are_refused():
    carry = {"h": jnp.zeros((2, 4)), "n": jnp.zeros((), jnp.int32)}
    fixed = FixedBufferStep(step, {"w": jnp.eye(4)}, _example(0), carry)
    obs, key = _example(1)
    with pytest.raises(ValueError, match="structure"):
        fixed((obs,))
    with pytest.raises(ValueError, match=r"leaf 0 has shape and dtype \(\(3, 4\)"):
        fixed((jnp.zeros((3, 4)), key))
    with pytest.raises(ValueError, match="leaf 1"):
        fixed((obs, key.astype(jnp.float32)))


def test_only_the_inputs_the_step_reads_get_a_slot():
    """A simulator state carries many fields the decode step never reads: they are neither
    slotted nor copied per call, and the step still sees their shapes."""
    def partial_step(params, inputs, carry):
        return {"y": inputs["read"] * params + inputs["ignored"].shape[0]}, carry + 1

    inputs = {"read": jnp.arange(3.0), "ignored": jnp.ones((5, 2))}
    fixed = FixedBufferStep(partial_step, jnp.float32(2.0), inputs, jnp.zeros((), jnp.int32))
    assert len(fixed.buffer_addresses()) == 3  # "read", the carry, the result
    out = fixed({"read": jnp.full(3, 4.0), "ignored": jnp.zeros((5, 2))})
    np.testing.assert_array_equal(out["y"], np.full(3, 13.0))
