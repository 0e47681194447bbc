"""Cholesky factorisation and solve of small dense matrices, one matrix per GPU thread, as
Pallas (Triton) kernels, for MJX's dense factorisations of a batch of envs on a GPU.

MJX factors nv x nv matrices with `jax.scipy.linalg.cho_factor` / `cho_solve` (mujoco-mjx
3.17.0): the Newton solver's Hessian at every iteration (`solver._update_gradient`), the mass
matrix (`smooth.factor_m` / `solve_m`) and the implicit integrator's M - h D
(`forward._implicit`). Batched over envs, XLA runs them as cuSOLVER's batched `potrf` and
cuBLAS's batched `trsm`, built for larger matrices: each call reads the batch several
times. Here each env is one thread's: its matrix's lower triangle is read once (the batch
along the lanes, so every load is one coalesced row of `block` envs), the factorisation is
written out entry by entry, ~n^3/6 multiply-adds in registers, and the factor written once;
the solve reads it and the right-hand side once each.

`cholesky_lower` and `solve_lower` take one matrix, as MJX calls them inside `vmap`; their
batching rule (`jax.custom_batching.custom_vmap`) runs the batched kernel over the mapped
axis. `dense_factorisations` replaces `cho_factor` and `cho_solve` by them while MJX is traced.
The arithmetic is the textbook order (each entry's sum over k ascending), not cuSOLVER's, so
the last bits differ from XLA's path, and with them, through contacts, an episode's later
steps.
"""

from __future__ import annotations

import contextlib
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pltriton

BLOCK = 128  # envs per program: one per thread of 4 warps


def _tril_index(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The lower triangle's (rows, cols), row-major: entry (i, j), j <= i, at i (i + 1) / 2 + j."""
    return np.tril_indices(n)


def _warps(block: int) -> pltriton.CompilerParams:
    """One env per thread: a warp per 32 envs."""
    return pltriton.CompilerParams(num_warps=max(1, block // 32))


def _slot(i: int, j: int) -> int:
    return i * (i + 1) // 2 + j


def _lanes(x: jnp.ndarray, rows: int, block: int) -> jnp.ndarray:
    """[B, r] -> [rows, B padded to `block`]: the batch along the lanes, rows padded to a power
    of two (Triton's block shapes). Padded envs hold zeros; their results are dropped."""
    b, r = x.shape
    pad_b = -(-b // block) * block - b
    return jnp.pad(x.T, ((0, rows - r), (0, pad_b)))


def _factor_batched(a: jnp.ndarray, block: int = BLOCK, interpret: bool = False) -> jnp.ndarray:
    """[B, n, n] -> [B, n, n]: the lower Cholesky factor of each matrix's lower triangle (zeros
    above the diagonal; NaN where a matrix is not positive definite, as cuSOLVER gives)."""
    b, n, _ = a.shape
    rows, cols = _tril_index(n)
    size = len(rows)
    padded = pl.next_power_of_2(size)
    x = _lanes(a[:, rows, cols].astype(jnp.float32), padded, block)

    def kernel(a_ref, l_ref):
        l = {}
        for j in range(n):
            for i in range(j, n):
                s = a_ref[_slot(i, j), :]
                for k in range(j):
                    s = s - l[i, k] * l[j, k]
                l[i, j] = jnp.sqrt(s) if i == j else s / l[j, j]
                l_ref[_slot(i, j), :] = l[i, j]

    lanes = pl.BlockSpec((padded, block), lambda i: (0, i))
    out = pl.pallas_call(kernel, grid=(x.shape[1] // block,), in_specs=[lanes], out_specs=lanes,
                         out_shape=jax.ShapeDtypeStruct(x.shape, jnp.float32), compiler_params=_warps(block),
                         interpret=interpret)(x)
    packed = out[:size, :b].T
    return jnp.zeros((b, n, n), jnp.float32).at[:, rows, cols].set(packed).astype(a.dtype)


def _solve_batched(l: jnp.ndarray, rhs: jnp.ndarray, block: int = BLOCK, interpret: bool = False) -> jnp.ndarray:
    """[B, n, n] lower factors L, [B, n] -> [B, n]: x with L L^T x = rhs, by forward then back
    substitution (only L's lower triangle is read)."""
    b, n, _ = l.shape
    rows, cols = _tril_index(n)
    size = len(rows)
    lx = _lanes(l[:, rows, cols].astype(jnp.float32), pl.next_power_of_2(size), block)
    bx = _lanes(rhs.astype(jnp.float32), pl.next_power_of_2(n), block)

    def kernel(l_ref, b_ref, x_ref):
        y = []
        for i in range(n):
            s = b_ref[i, :]
            for k in range(i):
                s = s - l_ref[_slot(i, k), :] * y[k]
            y.append(s / l_ref[_slot(i, i), :])
        x = [None] * n
        for i in reversed(range(n)):
            s = y[i]
            for k in range(i + 1, n):
                s = s - l_ref[_slot(k, i), :] * x[k]
            x[i] = s / l_ref[_slot(i, i), :]
            x_ref[i, :] = x[i]

    grid = (lx.shape[1] // block,)
    out = pl.pallas_call(
        kernel, grid=grid,
        in_specs=[pl.BlockSpec((lx.shape[0], block), lambda i: (0, i)), pl.BlockSpec((bx.shape[0], block), lambda i: (0, i))],
        out_specs=pl.BlockSpec((bx.shape[0], block), lambda i: (0, i)),
        out_shape=jax.ShapeDtypeStruct(bx.shape, jnp.float32), compiler_params=_warps(block),
        interpret=interpret)(lx, bx)
    return out[:n, :b].T.astype(rhs.dtype)


def _batched(fn):
    """fn over one matrix (and vector), batched by `fn`'s batched kernel under vmap."""
    def one(*args):
        return fn(*(x[None] for x in args))[0]

    wrapped = jax.custom_batching.custom_vmap(one)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        args = [x if batched else jnp.broadcast_to(x, (axis_size, *x.shape)) for x, batched in zip(args, in_batched)]
        return fn(*args), True

    return wrapped


def _kernels(interpret: bool):
    return (_batched(functools.partial(_factor_batched, interpret=interpret)),
            _batched(functools.partial(_solve_batched, interpret=interpret)))


_GPU_KERNELS = _kernels(interpret=False)
_INTERPRETED = _kernels(interpret=True)


def cholesky_lower(a: jnp.ndarray, interpret: bool = False) -> jnp.ndarray:
    """[n, n] -> the lower Cholesky factor of `a`'s lower triangle (zeros above); under vmap one
    kernel over the batch. `interpret`: run the kernel's body as JAX operations (any backend)."""
    return (_INTERPRETED if interpret else _GPU_KERNELS)[0](a)


def solve_lower(l: jnp.ndarray, rhs: jnp.ndarray, interpret: bool = False) -> jnp.ndarray:
    """x [n] with L L^T x = rhs [n], for a lower factor L [n, n]; under vmap one kernel."""
    return (_INTERPRETED if interpret else _GPU_KERNELS)[1](l, rhs)


MAX_N = 64  # larger matrices keep XLA's path: the unrolled kernel grows as n^3


def _fits(a) -> bool:
    return a.ndim == 2 and a.shape[0] == a.shape[1] <= MAX_N and a.dtype == jnp.float32


def cho_factor(a, lower: bool = False, overwrite_a: bool = False, check_finite: bool = True, *, interpret: bool = False):
    """`jax.scipy.linalg.cho_factor` of one float32 matrix through `cholesky_lower` (the same
    (c, lower) pair: c the factor, zeros in its other triangle); anything else through JAX's."""
    a = jnp.asarray(a)
    if not _fits(a):
        return _ORIGINAL["cho_factor"](a, lower=lower)
    factor = cholesky_lower(a if lower else a.T, interpret)
    return (factor if lower else factor.T), lower


def cho_solve(c_and_lower, b, overwrite_b: bool = False, check_finite: bool = True, *, interpret: bool = False):
    """`jax.scipy.linalg.cho_solve` through `solve_lower` for one float32 factor and a vector
    or matrix right-hand side (each column solved); anything else through JAX's."""
    c, lower = c_and_lower
    c, b = jnp.asarray(c), jnp.asarray(b)
    if not (_fits(c) and b.dtype == jnp.float32 and b.ndim in (1, 2) and b.shape[0] == c.shape[0]):
        return _ORIGINAL["cho_solve"]((c, lower), b)
    l = c if lower else c.T
    if b.ndim == 1:
        return solve_lower(l, b, interpret)
    return jax.vmap(lambda col: solve_lower(l, col, interpret), in_axes=1, out_axes=1)(b)


_ORIGINAL = {"cho_factor": jax.scipy.linalg.cho_factor, "cho_solve": jax.scipy.linalg.cho_solve}


@contextlib.contextmanager
def dense_factorisations(enabled: bool = True, interpret: bool = False):
    """While code is traced inside it (with `enabled`), `jax.scipy.linalg.cho_factor` and
    `cho_solve` (MJX calls them by those names) run as this module's kernels. Re-entrant;
    patches only tracing: a compiled program keeps whatever was traced."""
    linalg = jax.scipy.linalg
    if not enabled or getattr(linalg.cho_factor, "_kernel", False):
        yield
        return
    factor = functools.partial(cho_factor, interpret=interpret)
    solve = functools.partial(cho_solve, interpret=interpret)
    factor._kernel = solve._kernel = True
    linalg.cho_factor, linalg.cho_solve = factor, solve
    try:
        yield
    finally:
        linalg.cho_factor, linalg.cho_solve = _ORIGINAL["cho_factor"], _ORIGINAL["cho_solve"]
