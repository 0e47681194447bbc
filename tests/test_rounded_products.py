"""`rounded_products`: TF32 rounding of float32 values (nearest, ties to even, non-finite
values kept, differentiated as the identity), exact products of rounded operands, and a
function transform that rounds every product's operands, inside scans, while loops,
conditionals and checkpoints too."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import rounded_products as rp

ULP_AT_ONE = 2.0 ** -10  # TF32's spacing in [1, 2)


def test_rounding_is_to_the_nearest_tf32_value_ties_to_even():
    x = np.array([1.0, 1 + ULP_AT_ONE / 2, 1 + 3 * ULP_AT_ONE / 2, 1 + ULP_AT_ONE * 0.49, 1 + ULP_AT_ONE * 0.51,
                  -(1 + ULP_AT_ONE * 0.51), 0.0, -0.0], np.float32)
    want = np.array([1.0, 1.0, 1 + 2 * ULP_AT_ONE, 1.0, 1 + ULP_AT_ONE, -(1 + ULP_AT_ONE), 0.0, -0.0], np.float32)
    got = np.asarray(rp.round_to_tf32(jnp.asarray(x)))
    np.testing.assert_array_equal(got, want)
    assert np.signbit(got[-1])


def test_non_finite_values_are_kept_and_the_largest_floats_overflow_to_infinity():
    x = jnp.asarray([np.inf, -np.inf, np.nan, np.finfo(np.float32).max], jnp.float32)
    got = np.asarray(rp.round_to_tf32(x))
    assert got[0] == np.inf and got[1] == -np.inf and np.isnan(got[2]) and got[3] == np.inf


def test_rounded_values_have_ten_fraction_bits_and_stay_within_half_a_tf32_ulp():
    x = np.asarray(jax.random.normal(jax.random.key(0), (10_000,)) * 10.0 ** jax.random.randint(
        jax.random.key(1), (10_000,), -30, 30), np.float32)
    r = np.asarray(rp.round_to_tf32(jnp.asarray(x)))
    assert not (r.view(np.uint32) & 0x1FFF).any()  # the 13 fraction bits TF32 drops are zero
    np.testing.assert_array_equal(np.asarray(rp.round_to_tf32(jnp.asarray(r))), r)  # idempotent
    assert (np.abs(r.astype(np.float64) - x) <= np.abs(x) * 2.0 ** -11).all()


def test_products_of_rounded_operands_are_exact_in_float32():
    """Why rounding first makes kernels agree: 11-bit significands multiply exactly in 24 bits."""
    a, b = (np.asarray(rp.round_to_tf32(jax.random.normal(jax.random.key(k), (100_000,)))) for k in (2, 3))
    np.testing.assert_array_equal((a * b).astype(np.float64), a.astype(np.float64) * b.astype(np.float64))
    a, b = (np.asarray(jax.random.normal(jax.random.key(k), (100_000,)), np.float32) for k in (2, 3))
    assert ((a * b).astype(np.float64) != a.astype(np.float64) * b.astype(np.float64)).any()  # unrounded: not


def _program(a, w):
    def body(c, _):
        return jnp.tanh(c @ w), None
    y, _ = jax.lax.scan(body, a, None, length=3)
    z = jax.lax.while_loop(lambda c: c[1] < 2, lambda c: (c[0] @ w, c[1] + 1), (y, 0))[0]
    z = jax.lax.cond(z.sum() > 0, lambda q: q @ w, lambda q: -q @ w, z)
    z = jax.checkpoint(lambda q: jnp.sin(q @ w))(z)  # an open sub-program
    return {"out": z, "conv": jax.lax.conv(a[None, None], w[None, None, :4, :4], (1, 1), "VALID")}


def _by_hand(a, w):
    r = rp.round_to_tf32
    c = a
    for _ in range(3):
        c = jnp.tanh(r(c) @ r(w))
    for _ in range(2):
        c = r(c) @ r(w)
    c = r(c) @ r(w) if c.sum() > 0 else r(-c) @ r(w)
    c = jnp.sin(r(c) @ r(w))
    return {"out": c, "conv": jax.lax.conv(r(a)[None, None], r(w)[None, None, :4, :4], (1, 1), "VALID")}


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_every_product_in_nested_programs_takes_rounded_operands(jit):
    a = jax.random.normal(jax.random.key(4), (4, 8))
    w = jax.random.normal(jax.random.key(5), (8, 8)) / 3
    fn = rp.with_tf32_operands(_program)
    got = (jax.jit(fn) if jit else fn)(a, w)
    want = _by_hand(a, w)
    for k in want:
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(want[k]))
    assert not np.array_equal(np.asarray(_program(a, w)["out"]), np.asarray(want["out"]))


def test_non_array_arguments_pass_through_and_integer_products_are_left_alone():
    def fn(x, n, scale=1):
        return {"f": (x @ x.T) * scale, "i": jnp.arange(n) @ jnp.arange(n)}
    x = jnp.full((2, 3), 1 + ULP_AT_ONE / 4, jnp.float32)  # rounds to 1
    got = rp.with_tf32_operands(fn)(x, 5, scale=2)
    np.testing.assert_array_equal(np.asarray(got["f"]), np.full((2, 2), 6.0, np.float32))
    assert int(got["i"]) == 30


def test_a_rounded_product_differentiates_through_the_rounding_as_the_identity():
    a = jax.random.normal(jax.random.key(6), (3, 5))
    b = jax.random.normal(jax.random.key(7), (5, 2))
    grad_a = jax.grad(lambda a: rp.with_tf32_operands(lambda a, b: (a @ b).sum())(a, b))(a)
    np.testing.assert_array_equal(np.asarray(grad_a), np.asarray(jnp.ones((3, 2)) @ rp.round_to_tf32(b).T))
