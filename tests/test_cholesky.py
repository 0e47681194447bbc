"""envs.cholesky: the kernels (interpret mode) against float64 and against JAX's cho_factor /
cho_solve, batched and not, either triangle, and the patch MJX is traced under."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import cholesky, physics


def _spd(batch, n, seed=0, spread=20.0):
    """[batch, n, n] float32 symmetric positive definite: with the default `spread`, conditioned
    like MJX's Hessians (a few large eigenvalues, the rest near a small diagonal)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(batch, n, 2)) * rng.uniform(0.5, spread, (batch, 1, 2))
    a = x @ np.swapaxes(x, 1, 2) + np.eye(n) * rng.uniform(0.05, 2, (batch, n, 1))
    return a.astype(np.float32), rng.normal(size=(batch, n)).astype(np.float32)


def test_factor_and_solve_equal_float64_for_a_batch_not_a_multiple_of_the_block():
    a, b = _spd(37, 7)
    l = np.asarray(cholesky._factor_batched(jnp.asarray(a), block=32, interpret=True))
    l64 = np.linalg.cholesky(a.astype(np.float64))
    assert (np.triu(l, 1) == 0).all()
    jax_l = np.asarray(jax.vmap(jnp.linalg.cholesky)(a))
    # as close to float64 as JAX's own float32 factor, entry by entry relative to each matrix's scale
    scale = np.abs(l64).max((1, 2), keepdims=True)
    assert np.abs(l - l64).max() / scale.min() < 1e-5
    assert (np.abs(l - l64) / scale).max() <= 2 * (np.abs(jax_l - l64) / scale).max() + 1e-7
    x = np.asarray(cholesky._solve_batched(jnp.asarray(l), jnp.asarray(b), block=32, interpret=True))
    want = np.linalg.solve(a.astype(np.float64), b.astype(np.float64)[..., None])[..., 0]
    jax_x = np.asarray(jax.vmap(lambda a, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b))(a, b))
    assert np.abs(x - want).max() <= 2 * np.abs(jax_x - want).max() + 1e-6


@pytest.mark.parametrize("lower", [False, True])
def test_cho_factor_and_cho_solve_equal_jax_under_vmap_and_alone(lower):
    a, b = _spd(5, 6, seed=1, spread=2.0)
    ours = jax.vmap(lambda a, b: cholesky.cho_solve(cholesky.cho_factor(a, lower, interpret=True), b, interpret=True))
    theirs = jax.vmap(lambda a, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a, lower), b))
    np.testing.assert_allclose(ours(a, b), theirs(a, b), rtol=1e-4, atol=1e-5)
    c, got_lower = cholesky.cho_factor(a[0], lower, interpret=True)
    want_c, _ = jax.scipy.linalg.cho_factor(a[0], lower)
    assert got_lower == lower
    np.testing.assert_allclose(c, want_c, rtol=1e-5, atol=1e-6)  # the same triangle, zeros in the other
    rhs = np.stack([b[0], 2 * b[1]], 1)  # a matrix right-hand side: each column solved
    np.testing.assert_allclose(cholesky.cho_solve((c, lower), rhs, interpret=True),
                               jax.scipy.linalg.cho_solve((want_c, lower), rhs), rtol=1e-4, atol=1e-5)


def test_nested_vmap_and_an_unbatched_argument():
    a, b = _spd(6, 4, seed=2, spread=2.0)
    a2, b2 = a.reshape(2, 3, 4, 4), b.reshape(2, 3, 4)
    nested = jax.vmap(jax.vmap(lambda a, b: cholesky.solve_lower(cholesky.cholesky_lower(a, True), b, True)))
    want = np.linalg.solve(a2.astype(np.float64), b2.astype(np.float64)[..., None])[..., 0]
    np.testing.assert_allclose(nested(a2, b2), want, rtol=1e-3, atol=1e-4)
    l0 = cholesky.cholesky_lower(a[0], True)  # one factor, many right-hand sides
    shared = jax.vmap(lambda b: cholesky.solve_lower(l0, b, True))(b)
    np.testing.assert_allclose(shared, np.linalg.solve(a[0].astype(np.float64), b.T.astype(np.float64)).T,
                               rtol=1e-3, atol=1e-4)


def test_not_positive_definite_gives_nan_as_jax_does():
    a = -np.eye(3, dtype=np.float32)
    c, _ = cholesky.cho_factor(a, True, interpret=True)
    assert np.isnan(np.asarray(c)[0, 0])


def _traced(fn, *args):
    """fn's jaxpr, traced anew (JAX caches a function's trace, not what it looked up then)."""
    return str(jax.make_jaxpr(lambda *x: fn(*x))(*args))


def test_the_patch_routes_mjx_sized_float32_matrices_to_the_kernels_only():
    a, b = _spd(2, 5)
    call = jax.vmap(lambda a, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b))

    with cholesky.dense_factorisations(interpret=True):
        with cholesky.dense_factorisations(interpret=True):  # re-entrant
            patched = _traced(call, a, b)
        big = _traced(lambda a: jax.scipy.linalg.cho_factor(a)[0], np.eye(cholesky.MAX_N + 1, dtype=np.float32))
        assert jax.scipy.linalg.cho_factor is not cholesky._ORIGINAL["cho_factor"]
    assert patched.count("pallas_call") == 2 and "cholesky" not in patched
    assert "pallas_call" not in big  # larger than MAX_N: JAX's own
    assert jax.scipy.linalg.cho_factor is cholesky._ORIGINAL["cho_factor"]  # restored
    assert jax.scipy.linalg.cho_solve is cholesky._ORIGINAL["cho_solve"]
    with cholesky.dense_factorisations(enabled=False):
        assert "pallas_call" not in _traced(call, a, b)


def test_every_dense_factorisation_of_an_mjx_step_runs_on_the_kernels(compiled):
    """The Newton solver's Hessian, the mass matrix and the implicit integrator's matrix: no
    cuSOLVER / cuBLAS primitive is left in a batched physics step traced under the patch.
    `PhysicsConfig.cholesky_kernel` patches only on a single GPU: here, XLA's path."""
    m, d = compiled.env.model, compiled.start([0, 1]).data
    step = jax.vmap(lambda d: physics.step(m, d))
    with cholesky.dense_factorisations(interpret=True):
        patched = _traced(step, d)
    assert "cholesky" not in patched and "triangular_solve" not in patched
    assert patched.count("pallas_call") >= 5  # 3 factors, their solves
    cpu = _traced(jax.vmap(lambda d: physics.step(m, d, physics.PhysicsConfig(cholesky_kernel=True))), d)
    assert "pallas_call" not in cpu and "cholesky" in cpu
