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

import jax
import jax.numpy as jnp

from heisd_jax import jaxpr_rewrite

_TF32_DROPPED_BITS = 13  # float32 keeps 23 fraction bits, TF32 10
_TF32_KEPT = 0xFFFFFFFF & ~((1 << _TF32_DROPPED_BITS) - 1)  # sign, exponent and TF32's fraction bits
_EXPONENT = 0x7F800000


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


def _rounded_product(primitive):
    """A `jaxpr_rewrite` rule: primitive with its two factors rounded first."""

    def rule(invals, **params):
        return primitive.bind(*[_round_operand(x) for x in invals[:2]], *invals[2:], **params)

    return rule


_RULES = {"dot_general": _rounded_product(jax.lax.dot_general_p),
          "conv_general_dilated": _rounded_product(jax.lax.conv_general_dilated_p)}


def with_tf32_operands(fn):
    """fn with every float32 matrix product's (and convolution's) operands rounded to TF32
    (`round_to_tf32`) first. Arguments that are not arrays (configs) pass through as static
    values; the result has fn's structure."""
    return jaxpr_rewrite.with_rules(fn, _RULES)
