"""One configuration per method: each method's default config is the library's config (the
shipped heisd is `HybridConfig()`), its settings are that config's fields by name (a round
trip key=value -> config -> key=value), the implied settings and the datastore's calibration
fill what is not given, and bad keys and values are refused by name."""

import dataclasses

import pytest

from heisd_jax import acceptance, budget, hybrid, spec_decode
from heisd_jax.harness import methods


def test_library_defaults_are_the_shipped_methods():
    assert methods.config("heisd") == methods.Config(decode=hybrid.HybridConfig()) == methods.get("heisd").default
    assert methods.config("drafter") == methods.Config(decode=spec_decode.SpecConfig())
    assert methods.config("ar") == methods.Config(numerics=methods.Numerics())
    h = hybrid.HybridConfig()
    assert (h.seq, h.skip, h.budget) == (acceptance.SeqRelaxedConfig(), acceptance.SkipConfig(), budget.BudgetConfig())
    assert (h.seq.r_max, h.seq.r_seq, h.recent_candidates, h.skip.source, h.budget.mode) == (9, 24, 4, "recent", "auto")
    # The paper's values, a named preset; the retrieval method is its retrieval side, token-relaxed, no skip.
    assert (hybrid.PAPER.seq.r_max, hybrid.PAPER.seq.r_seq, hybrid.PAPER.skip.source) == (15, 42, "retrieval")
    r = methods.config("retrieval").decode
    assert r == dataclasses.replace(hybrid.PAPER, mode="retrieval", acceptance="token_relaxed",
                                    skip=dataclasses.replace(hybrid.PAPER.skip, enabled=False))
    assert methods.settings("heisd")["r_max"].default == 9 and methods.settings("retrieval")["r_max"].default == 15


@pytest.mark.parametrize("name,given", [
    ("heisd", {"budget": "fixed", "continuation": "ar"}),
    ("heisd", {"budget_trees": "4x2x8/2x2x4", "budget_margin": 0.2, "skip_source": "retrieval", "tau_on": 3.0}),
    ("heisd", {"target_scale": "llama2-7b", "dtype": "bfloat16", "r_max": 15, "skip": False}),
    ("retrieval", {"mode": "hybrid", "retrieval_acceptance": "seq_relaxed", "skip_eps": 0.1, "min_dwell": 2}),
    ("drafter", {"acceptance": "token_relaxed", "relax_bins": 9, "top_k": 4, "depth": 2, "total_tokens": 8}),
    ("ar", {"matmul_precision": "default", "unroll": True}),
    ("expert", {"gain": 1.0, "action_noise": 0.1}),
])
def test_settings_round_trip_through_the_config(name, given):
    cfg = methods.config(name, given)
    back = methods.settings_of(name, cfg)
    assert {k: back[k] for k in given} == given
    assert methods.config(name, back) == cfg
    assert methods.settings_of(name, methods.get(name).default) == methods.settings_of(name, methods.config(name))


def test_sweep_keys_reach_the_nested_config():
    (n1, s1), (n2, s2), (n3, s3) = methods.parse_method_list(
        "heisd:budget=fixed,continuation=ar;drafter:acceptance=token_relaxed,relax_bins=9;"
        "heisd:target_scale=llama2-7b,dtype=bfloat16")
    h = methods.config(n1, s1).decode
    assert (h.budget.mode, h.continuation) == ("fixed", "ar")
    assert methods.config(n2, s2).decode == spec_decode.SpecConfig(acceptance="token_relaxed", relax_bins=9)
    c = methods.config(n3, s3)
    assert (c.numerics.target_scale, c.numerics.dtype, c.decode) == ("llama2-7b", "bfloat16", hybrid.HybridConfig())


def test_implied_settings_and_calibration_fill_what_is_not_given():
    # heisd's default: relaxed retrieved actions (and verify-skip), strict trees after them.
    h = methods.config("heisd").decode
    assert (h.spec.acceptance, h.acceptance, h.skip.enabled, h.lossless) == ("strict", "seq_relaxed", True, False)
    strict = methods.config("heisd", {"acceptance": "strict"}).decode  # given: lossless unless asked otherwise
    assert strict.lossless and strict.spec.relax_bins == 0 and strict.acceptance == "strict"
    relaxed = methods.config("heisd", {"acceptance": "token_relaxed"}).decode  # the paper's kind of trees
    assert (relaxed.spec.relax_bins, relaxed.acceptance, relaxed.skip.enabled) == (acceptance.RELAX_BINS,
                                                                                   "seq_relaxed", True)
    assert methods.config("drafter", {"acceptance": "token_relaxed"}).decode.relax_bins == acceptance.RELAX_BINS
    assert methods.config("drafter", {"acceptance": "token_relaxed", "relax_bins": 3}).decode.relax_bins == 3
    assert methods.config("heisd", {"acceptance": "strict", "retrieval_acceptance": "seq_relaxed",
                                    "skip": False}).decode.acceptance == "seq_relaxed"
    assert not methods.config("heisd", {"recent_candidates": 0}).decode.skip.enabled  # no candidates to repeat
    cal = {"metric_scales": [0.1, 0.2, 0.3, 0.4, 0.5], "boundary": {"tau_on": 2.0, "tau_off": 1.0, "min_dwell": 4},
           "skip_eps": 0.02}
    h = methods.config("heisd", {"tau_on": 3.0}, cal).decode
    assert (h.boundary.tau_on, h.boundary.tau_off, h.boundary.min_dwell) == (3.0, 1.0, 4)
    assert h.metric.scales == (0.1, 0.2, 0.3, 0.4, 0.5) and h.skip.eps == 0.02
    assert methods.config("heisd", {"skip_eps": 0.5}, cal).decode.skip.eps == 0.5


def test_bad_keys_and_values_are_refused_by_name():
    with pytest.raises(ValueError, match=r"unknown settings \['budjet'\]; valid: .*budget, budget_trees"):
        methods.check_settings("heisd", {"budjet": "fixed"})
    with pytest.raises(ValueError, match="unknown budget 'sometimes'; valid: auto, fixed"):
        methods.check_settings("heisd", {"budget": "sometimes"})
    with pytest.raises(ValueError, match="unknown acceptance 'seq_relaxed'; valid: strict, token_relaxed"):
        methods.check_settings("drafter", {"acceptance": "seq_relaxed"})
    with pytest.raises(ValueError, match="unknown retrieval_acceptance 'loose'; valid: strict, token_relaxed, seq_"):
        methods.parse_method_list("retrieval:retrieval_acceptance=loose")
    with pytest.raises(ValueError, match="relax_bins is only used with acceptance='token_relaxed'"):
        methods.check_settings("heisd", {"relax_bins": 9})  # the default trees are strict
    with pytest.raises(ValueError, match="TOPKxDEPTHxTOTAL"):
        methods.check_settings("heisd", {"budget_trees": "4x2"})
    with pytest.raises(ValueError, match=r"unknown settings \['skip'\]; valid: dtype"):
        methods.check_settings("drafter", {"skip": True})


def test_a_preset_stands_for_its_settings_and_given_ones_replace_its_own():
    b16 = methods.config("heisd", {"preset": "batch16"}).decode
    assert (b16.budget.mode, b16.continuation, b16.n_candidates, b16.recent_candidates, b16.row_buckets) == \
        ("fixed", "ar", 0, 1, 4)
    assert (b16.seq.r_max, b16.seq.r_seq, b16.skip.repeat_r_max, b16.skip.repeat_r_seq, b16.skip.enabled) == \
        (2, 6, 9, 24, True)
    b1 = methods.config("heisd", {"preset": "batch1"}).decode
    assert (b1.budget.mode, b1.spec.top_k, b1.spec.depth, b1.spec.total_tokens) == ("fixed", 4, 2, 8)
    # Given settings win; the checked settings are the preset's, so a result records what ran.
    (name, given), = methods.parse_method_list("heisd:preset=batch16,row_buckets=8")
    assert given == {**methods.PRESETS["heisd"]["batch16"], "row_buckets": 8}
    assert methods.check_settings(name, given) == given
    assert methods.config(name, given).decode == dataclasses.replace(b16, row_buckets=8)
    with pytest.raises(ValueError, match="method 'heisd': unknown preset 'batch8'; valid: batch1, batch16"):
        methods.check_settings("heisd", {"preset": "batch8"})
    with pytest.raises(ValueError, match="method 'ar': unknown preset 'batch16'; valid: none"):
        methods.parse_method_list("ar:preset=batch16")
    for name, named in methods.PRESETS.items():  # every preset is settings its method takes
        for preset, settings in named.items():
            assert methods.check_settings(name, {"preset": preset}) == settings


def test_every_declared_setting_is_some_methods():
    keys = {k for name in methods.METHODS for k in methods.settings(name)}
    declared = {s.key for table in methods.SETTINGS.values() for s in table.values()}
    assert declared == keys


def test_a_method_computes_in_its_targets_own_dtype_unless_given():
    """Numerics' dtype defaults to the dtype the target's parameters come in (its checkpoint's):
    a bfloat16-stored target decodes in bfloat16, a float32 one in float32; a given dtype wins;
    parameters in mixed dtypes are refused by name."""
    import jax
    import jax.numpy as jnp

    import tiny_models
    from heisd_jax import vla

    params = vla.init_params(tiny_models.CFG, jax.random.PRNGKey(0))
    bf16 = jax.tree.map(lambda x: x.astype(jnp.bfloat16), params)
    for target, given, expected in [(bf16, {}, "bfloat16"), (params, {}, "float32"),
                                    (bf16, {"dtype": "float32"}, "float32"), (params, {"dtype": "bfloat16"}, "bfloat16")]:
        cfg, out = methods.in_numerics(tiny_models.CFG, methods.config("ar", given).numerics, target)
        assert cfg.dtype == expected and {str(x.dtype) for x in jax.tree.leaves(out)} == {expected}
    mixed = {**params, "head": jax.tree.map(lambda x: x.astype(jnp.bfloat16), params["head"])}
    with pytest.raises(ValueError, match=r"target parameters in \['bfloat16', 'float32'\]"):
        methods.in_numerics(tiny_models.CFG, methods.Numerics(), mixed)


def test_fused_attention_is_a_numerics_setting_refused_where_it_cannot_run():
    import jax

    import tiny_models

    numerics = methods.config("ar", {"attention": "cudnn", "dtype": "bfloat16"}).numerics
    assert numerics.attention == "cudnn"
    with pytest.raises(ValueError, match="attention 'bad'"):
        methods.config("ar", {"attention": "bad"})
    if jax.default_backend() != "gpu":  # refused from the config, before any weight is made
        with pytest.raises(ValueError, match="runs on a GPU, not on cpu; valid here: auto, xla"):
            methods.numerics_config(tiny_models.CFG, numerics, "bfloat16")
    f32 = methods.numerics_config(tiny_models.CFG, methods.Numerics(), "float32")
    with pytest.raises(ValueError, match="not float32; valid for float32: xla"):
        dataclasses.replace(f32, attention="cudnn")
    # the default ("auto") is resolved in the model config: what runs and keys a cost table
    assert methods.Numerics().attention == "auto" and f32.attention == "xla"
    if jax.default_backend() != "gpu":
        assert methods.numerics_config(tiny_models.CFG, methods.Numerics(dtype="bfloat16"), "bfloat16").attention == "xla"


def test_patchify_is_a_numerics_setting_that_keys_cost_tables():
    import tiny_models
    from heisd_jax import cost_model, hybrid

    numerics = methods.config("heisd", {"patchify": "dense"}).numerics
    cfg = methods.numerics_config(tiny_models.CFG, numerics, "float32")
    assert numerics.patchify == cfg.patchify == "dense"
    assert methods.numerics_config(tiny_models.CFG, methods.Numerics(), "float32").patchify == "conv"
    with pytest.raises(ValueError, match="unknown patchify 'bad'; valid: conv, dense"):
        methods.config("ar", {"patchify": "bad"})
    # a table measured with one form does not price the other; the default's key is unchanged
    hcfg = hybrid.HybridConfig()
    conv_key = cost_model.table_key(tiny_models.CFG, hcfg, 1)
    assert "patchify" not in conv_key and cost_model.table_key(cfg, hcfg, 1)["patchify"] == "dense"


def test_what_does_not_fit_the_targets_cache_is_refused_from_configs_alone():
    # The shipped target: every decoding method's defaults fit; more candidates than its cache
    # holds are refused with the limit, as make_policy would refuse them after loading.
    for name in methods.DECODING_METHODS:
        methods.check_fits(name)
    methods.check_fits("heisd", n_candidates=8)
    with pytest.raises(ValueError, match="n_candidates \\+ recent_candidates must be <= 12"):
        methods.check_fits("heisd", n_candidates=16)
    with pytest.raises(ValueError, match="cache slots"):
        methods.check_fits("drafter", top_k=16, depth=6, total_tokens=96)
