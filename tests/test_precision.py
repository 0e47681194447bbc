"""The target's and the drafter's matrix products run at VLAConfig.matmul_precision: in full
float32 by default (so a state decodes to the same tokens at every batch size on GPUs whose
default would use TF32 for some shapes), at XLA's choice with "default", with one pinned
tensor-core algorithm with "bf16" (and "tf32", which needs a GPU), with every operand rounded
to TF32 first with "tf32_rounded", and untouched in bfloat16; bad values are refused with the
valid ones named."""

import dataclasses
import re

import jax
import jax.extend.core as jcore
import numpy as np
import pytest

from heisd_jax import drafter, spec_decode, vla
from heisd_jax.harness import methods
from tests.tiny_models import CFG, obs

SPEC = spec_decode.SpecConfig(top_k=4, depth=3, total_tokens=10)


def _decode_jaxpr(cfg: vla.VLAConfig, spec=None):
    params = vla.init_params(cfg, jax.random.PRNGKey(0))
    if spec is not None:
        params = {"target": params, "drafter": drafter.init_params(cfg, jax.random.PRNGKey(1))}
    return jax.make_jaxpr(lambda p, o: spec_decode._decode_action(p, o, cfg, spec))(params, obs(batch=2))


def _products(cfg: vla.VLAConfig, spec=None) -> list[str]:
    """The precision of every dot_general / conv in the traced decode (nested programs included)."""
    text = str(_decode_jaxpr(cfg, spec))
    found = re.findall(r"(?:dot_general|conv_general_dilated)\[[^\]]*?precision=([^\n]*)", text)
    assert found, "no matrix product found in the traced decode"
    return found


@pytest.mark.parametrize("spec", [None, SPEC], ids=["ar", "drafter_sd"])
def test_every_product_is_full_float32_by_default(spec):
    assert CFG.matmul_precision == "float32"
    assert all("HIGHEST" in p for p in _products(CFG, spec))


@pytest.mark.parametrize("change", [dict(matmul_precision="default"), dict(dtype="bfloat16")])
def test_default_precision_and_bfloat16_leave_products_to_xla(change):
    assert not any("HIGHEST" in p for p in _products(dataclasses.replace(CFG, **change)))


def test_bf16_pins_one_algorithm_for_every_product():
    found = _products(dataclasses.replace(CFG, matmul_precision="bf16"), SPEC)
    assert all("BF16_BF16_F32" in p for p in found)


@pytest.mark.skipif(jax.default_backend() == "gpu", reason="TF32 runs on GPUs")
@pytest.mark.parametrize("name", ["tf32", "tf32x3", "bf16x9"])
def test_gpu_only_algorithms_without_a_gpu_are_refused_before_tracing(name):
    with pytest.raises(ValueError, match=f'"{name}" needs a GPU.*valid here: float32, default, bf16, bf16x3, bf16x6, tf32_rounded, bf16_invariant(\n|$)'):
        _products(dataclasses.replace(CFG, matmul_precision=name))


@pytest.mark.parametrize("name,algorithm", [("bf16x3", "BF16_BF16_F32_X3"), ("bf16x6", "BF16_BF16_F32_X6")])
def test_split_bfloat16_algorithms_pin_every_product(name, algorithm):
    found = _products(dataclasses.replace(CFG, matmul_precision=name), SPEC)
    assert all(p.startswith(algorithm) or f"{algorithm}," in p or f"{algorithm})" in p for p in found), found


def test_bad_precision_is_refused_with_the_valid_ones():
    with pytest.raises(ValueError, match="float32, default, tf32, bf16, tf32x3, bf16x3, bf16x6, bf16x9, tf32_rounded"):
        dataclasses.replace(CFG, matmul_precision="fp8")
    with pytest.raises(ValueError, match="matmul_precision"):
        methods.check_settings("ar", {"matmul_precision": "fp8"})


def test_method_setting_reaches_the_config():
    cfg, _ = methods.in_dtype(CFG, "float32", {}, matmul_precision="default")
    assert cfg.matmul_precision == "default" and methods.Numerics().matmul_precision == "float32"
    cfg, _ = methods.in_numerics(CFG, methods.config("ar", {"unroll": "true"}).numerics, {})
    assert cfg.unroll and not methods.Numerics().unroll and methods.check_settings("ar", {"unroll": "true"})["unroll"]


def _is_rounding(eqn) -> bool:
    """Whether eqn is `rounded_products.round_to_tf32`: its custom-derivative call whose
    result a bitcast to float32 makes."""
    if eqn is None or eqn.primitive.name != "custom_jvp_call":
        return False
    inner = eqn.params["call_jaxpr"].jaxpr
    made_by = {v: e for e in inner.eqns for v in e.outvars}
    last = made_by.get(inner.outvars[0])
    return last is not None and last.primitive.name == "bitcast_convert_type" and last.params["new_dtype"] == np.float32


def _unrounded_operands(jaxpr) -> tuple[int, int]:
    """(float32 products and convolutions, those with an operand not rounded to TF32 just
    before) over a jaxpr and every program nested in it."""
    made_by = {v: e for e in jaxpr.eqns for v in e.outvars}
    total = unrounded = 0
    for e in jaxpr.eqns:
        if e.primitive.name in ("dot_general", "conv_general_dilated") and e.invars[0].aval.dtype == np.float32:
            total += 1
            unrounded += any(isinstance(v, jcore.Literal) or not _is_rounding(made_by.get(v)) for v in e.invars[:2])
        for sub in jcore.jaxprs_in_params(e.params):
            t, u = _unrounded_operands(sub)
            total, unrounded = total + t, unrounded + u
    return total, unrounded


@pytest.mark.parametrize("spec", [None, SPEC], ids=["ar", "drafter_sd"])
def test_tf32_rounded_rounds_the_operands_of_every_product(spec):
    cfg = dataclasses.replace(CFG, matmul_precision="tf32_rounded")
    total, unrounded = _unrounded_operands(_decode_jaxpr(cfg, spec).jaxpr)
    assert total > 10 and unrounded == 0
    assert _unrounded_operands(_decode_jaxpr(CFG, spec).jaxpr)[1] > 0  # the check sees unrounded ones
    if jax.default_backend() != "gpu":  # no TF32 units: the exact products in float32
        assert all("HIGHEST" in p for p in _products(cfg, spec))


def test_tf32_rounded_logits_stay_near_float32s():
    params = vla.init_params(CFG, jax.random.PRNGKey(0))
    full, _, _ = jax.jit(vla.prefill, static_argnums=1)(params, CFG, obs(batch=3))
    cfg = dataclasses.replace(CFG, matmul_precision="tf32_rounded")
    rounded, _, _ = jax.jit(vla.prefill, static_argnums=1)(params, cfg, obs(batch=3))
    diff = np.abs(np.asarray(full) - np.asarray(rounded))
    assert 0 < diff.max() < 1e-2 * np.abs(np.asarray(full)).max()
