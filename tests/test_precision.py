"""The target's and the drafter's matrix products run at VLAConfig.matmul_precision: in full
float32 by default (so a state decodes to the same tokens at every batch size on GPUs whose
default would use TF32 for some shapes), at XLA's choice with "default", with one pinned
tensor-core algorithm with "bf16" (and "tf32", which needs a GPU), and untouched in bfloat16;
bad values are refused with the valid ones named."""

import dataclasses
import re

import jax
import pytest

from heisd_jax import drafter, methods, spec_decode, vla
from tests.tiny_models import CFG, obs

SPEC = spec_decode.SpecConfig(top_k=4, depth=3, total_tokens=10)


def _products(cfg: vla.VLAConfig, spec=None) -> list[str]:
    """The precision of every dot_general / conv in the traced decode (nested programs included)."""
    params = vla.init_params(cfg, jax.random.PRNGKey(0))
    if spec is not None:
        params = {"target": params, "drafter": drafter.init_params(cfg, jax.random.PRNGKey(1))}
    text = str(jax.make_jaxpr(lambda p, o: vla._decode_action(p, o, cfg, spec))(params, obs(batch=2)))
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
    with pytest.raises(ValueError, match=f'"{name}" needs a GPU.*valid here: float32, default, bf16, bf16x3, bf16x6(\n|$)'):
        _products(dataclasses.replace(CFG, matmul_precision=name))


@pytest.mark.parametrize("name,algorithm", [("bf16x3", "BF16_BF16_F32_X3"), ("bf16x6", "BF16_BF16_F32_X6")])
def test_split_bfloat16_algorithms_pin_every_product(name, algorithm):
    found = _products(dataclasses.replace(CFG, matmul_precision=name), SPEC)
    assert all(p.startswith(algorithm) or f"{algorithm}," in p or f"{algorithm})" in p for p in found), found


def test_bad_precision_is_refused_with_the_valid_ones():
    with pytest.raises(ValueError, match="float32, default, tf32, bf16, tf32x3, bf16x3, bf16x6, bf16x9"):
        dataclasses.replace(CFG, matmul_precision="fp8")
    with pytest.raises(ValueError, match="matmul_precision"):
        methods.check_settings("ar", {"matmul_precision": "fp8"})


def test_method_setting_reaches_the_config():
    cfg, _ = methods.in_dtype(CFG, "float32", {}, matmul_precision="default")
    assert cfg.matmul_precision == "default" and methods.ARSettings().matmul_precision == "float32"
    cfg, _ = methods.in_numerics(CFG, methods.ARSettings(unroll=True), {})
    assert cfg.unroll and not methods.ARSettings().unroll and methods.check_settings("ar", {"unroll": "true"})["unroll"]
