"""Matrix products whose float32 operands are first rounded to TF32, so that every kernel forms
the same products.

Why: XLA and cuBLAS choose a kernel per shape. Allowed TF32, a GPU can run large products on
TF32 tensor cores (operands cut to an 11-bit significand) and small ones (a batch-1 decode's
matrix-vector products) on float32 units, where tensor cores do not pay; then one state's
logits differ between batch sizes, and between a single-token pass and a tree pass, by TF32's
rounding, enough to flip a near-tied greedy token (a likely cause of the pinned "tf32"
algorithm's batch-1 / batch-256 disagreement: BENCHMARKS.md, the target's matrix-product
precision; docs/target.md says what is measured). Rounding each operand to the
nearest TF32 value first makes the kernel's choice irrelevant to the products: a product of
two 11-bit significands is exact in float32 (22 bits), on a tensor core or not, so kernels
differ only in the order they sum, as full-float32 kernels do, and tensor cores still run the
large products.

`with_tf32_operands(fn)` traces fn to a jaxpr and evaluates it with every float32
`dot_general` and `conv_general_dilated` operand rounded, inside the bodies of scans, while
loops, conditionals and checkpoints too, so a model needs no change
(`vla.at_config_precision` applies it for `VLAConfig.matmul_precision = "tf32_rounded"`).
"""

from __future__ import annotations

import functools

import jax
import jax.extend.core as jcore
import jax.numpy as jnp
import numpy as np

_TF32_DROPPED_BITS = 13  # float32 keeps 23 fraction bits, TF32 10
_TF32_KEPT = 0xFFFFFFFF & ~((1 << _TF32_DROPPED_BITS) - 1)  # sign, exponent and TF32's fraction bits
_EXPONENT = 0x7F800000
_ROUNDED_PRIMITIVES = ("dot_general", "conv_general_dilated")  # their first two operands are the factors


@jax.custom_jvp
def round_to_tf32(x: jnp.ndarray) -> jnp.ndarray:
    """Each float32 value to the nearest value with a 10-bit fraction (ties to even), as
    float32; infinities and NaNs unchanged, a value past TF32's largest finite to infinity.
    Differentiated as the identity (a straight-through estimate), so a rounded model trains."""
    bits = jax.lax.bitcast_convert_type(x, jnp.uint32)
    half = jnp.uint32((1 << (_TF32_DROPPED_BITS - 1)) - 1)
    lsb = (bits >> _TF32_DROPPED_BITS) & jnp.uint32(1)
    rounded = (bits + half + lsb) & jnp.uint32(_TF32_KEPT)
    finite = (bits & jnp.uint32(_EXPONENT)) != jnp.uint32(_EXPONENT)
    return jax.lax.bitcast_convert_type(jnp.where(finite, rounded, bits), jnp.float32)


@round_to_tf32.defjvp
def _round_to_tf32_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return round_to_tf32(x), dx


def _round_operand(x):
    return round_to_tf32(x) if x.dtype == jnp.float32 else x


def _eval(jaxpr: jcore.Jaxpr, consts, args):
    """Evaluates jaxpr on args (binding each equation into the caller's trace) with the
    factors of every product rounded and its nested programs transformed alike."""
    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    for v, x in zip(jaxpr.constvars, consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, args):
        env[v] = x
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        if eqn.primitive.name in _ROUNDED_PRIMITIVES:
            invals[:2] = [_round_operand(x) for x in invals[:2]]
        params = {k: _transform_param(v) for k, v in eqn.params.items()}
        outs = eqn.primitive.bind(*invals, **params)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, x in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                env[v] = x
    return [read(v) for v in jaxpr.outvars]


def _transform_closed(closed: jcore.ClosedJaxpr) -> jcore.ClosedJaxpr:
    """The same program with its products' factors rounded, and the same signature."""
    avals = [v.aval for v in closed.jaxpr.invars]
    new = jax.make_jaxpr(lambda *a: _eval(closed.jaxpr, closed.consts, a))(*avals)
    if [v.aval for v in new.jaxpr.invars] != avals or new.out_avals != closed.out_avals:
        raise TypeError("rounding a sub-program's products changed its signature")  # a bug here, not the caller's
    return new


def _transform_param(value):
    """A primitive's parameter with the programs it holds (a scan's body, a conditional's
    branches) rounded alike; anything else unchanged."""
    if isinstance(value, jcore.ClosedJaxpr):
        return _transform_closed(value)
    if isinstance(value, jcore.Jaxpr):  # an open program (a checkpoint's): no constants of its own
        new = _transform_closed(jcore.ClosedJaxpr(value, ()))
        if new.consts:
            raise NotImplementedError("rounding an open sub-program's products made constants")
        return new.jaxpr
    if isinstance(value, tuple) and value and all(isinstance(v, jcore.ClosedJaxpr) for v in value):
        return tuple(_transform_closed(v) for v in value)
    return value


def with_tf32_operands(fn):
    """fn with every float32 matrix product's (and convolution's) operands rounded to TF32
    (`round_to_tf32`) first. Arguments that are not arrays (configs) pass through as static
    values; the result has fn's structure."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        leaves, tree = jax.tree.flatten((args, kwargs))
        is_array = [isinstance(x, (jax.Array, np.ndarray, np.generic)) for x in leaves]
        arrays = [x for x, a in zip(leaves, is_array) if a]

        def flat_fn(*xs):
            it = iter(xs)
            a, k = jax.tree.unflatten(tree, [next(it) if arr else x for x, arr in zip(leaves, is_array)])
            return fn(*a, **k)

        closed, out_shape = jax.make_jaxpr(flat_fn, return_shape=True)(*arrays)
        outs = _eval(closed.jaxpr, closed.consts, arrays)
        return jax.tree.unflatten(jax.tree.structure(out_shape), outs)

    return wrapped
