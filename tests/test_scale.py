"""The function-preserving expansion (`heisd_jax.scale`): a tiny target widened, deepened,
given more heads, MLP units, vocabulary and prompt pads computes the same function in
float32 (up to summation order) through every pass the decoders use; bad scales are refused."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import drafter, scale, spec_decode as sd, target_model, vla
from heisd_jax.harness import methods

from tiny_models import CFG, aligned_pair, ar, obs as make_obs

P = CFG.n_patches
SCALES = {
    # width x2, +2 layers, +4 heads, +4 prompt pads, +8 vocabulary ids; vision as wide as the decoder
    "wide": scale.TargetScale(d_model=64, n_layers=4, n_heads=8, mlp_dim=96, vocab=CFG.vocab + 8, image_tokens=P + 4,
                              vision_width=64, vision_layers=2, vision_heads=8, vision_mlp=96),
    # head size x4 (rotary pairs spread), a vision tower narrower than the decoder (projected)
    "deep_heads": scale.TargetScale(d_model=128, n_layers=3, n_heads=4, mlp_dim=80, vocab=CFG.vocab,
                                    image_tokens=P + 3, vision_width=64, vision_layers=3, vision_heads=4,
                                    vision_mlp=72),
}
TOL = dict(rtol=1e-4, atol=2e-5)


@pytest.fixture(scope="module", params=list(SCALES))
def expanded(request):
    """A random target and drafter, and a target-drafter pair whose drafts are accepted,
    each with its expansion."""
    out = {}
    for name, (tp, dp) in {"random": (vla.init_params(CFG, jax.random.PRNGKey(0)),
                                      drafter.init_params(CFG, jax.random.PRNGKey(1))),
                           "aligned": aligned_pair(0.0)}.items():
        big_tp, big_cfg = scale.expand_target(tp, CFG, SCALES[request.param], "float32")
        out[name] = (tp, dp), (big_tp, scale.expand_drafter(dp, CFG, SCALES[request.param], "float32"), big_cfg)
    return out


def test_config_and_parameter_shapes(expanded):
    _, (big_tp, big_dp, cfg) = expanded["random"]
    assert cfg.prompt_len - CFG.prompt_len == cfg.image_pad > 0
    assert cfg.cache_slots - cfg.prompt_len == CFG.cache_slots - CFG.prompt_len  # the same room for drafts
    want = jax.eval_shape(lambda: vla.init_params(cfg, jax.random.PRNGKey(0)))
    assert jax.tree.map(lambda x: x.shape, big_tp) == jax.tree.map(lambda x: x.shape, want)
    want_d = jax.eval_shape(lambda: drafter.init_params(cfg, jax.random.PRNGKey(0)))
    assert jax.tree.map(lambda x: x.shape, big_dp) == jax.tree.map(lambda x: x.shape, want_d)


def test_prefill_is_exact(expanded):
    (tp, _), (big_tp, _, cfg) = expanded["random"]
    obs = make_obs(3)
    logits, hidden, x, _ = vla.prefill_features(tp, CFG, obs)
    big_logits, big_hidden, big_x, _ = vla.prefill_features(big_tp, cfg, obs)
    np.testing.assert_allclose(vla.action_logits(cfg, big_logits), vla.action_logits(CFG, logits), **TOL)
    d, pad = CFG.d_model, cfg.image_pad
    np.testing.assert_allclose(big_hidden[:, pad:, :d], hidden, **TOL)
    np.testing.assert_allclose(big_x[:, pad:, :d], x, **TOL)
    assert not np.any(np.asarray(big_hidden[:, pad:, d:]))  # the padded residual dims stay zero


def test_cached_decoding_and_tree_verification_are_exact(expanded):
    (tp, _), (big_tp, _, cfg) = expanded["random"]
    obs = make_obs(4)
    tokens = ar(tp, obs)
    np.testing.assert_array_equal(jax.jit(lambda p, o: target_model.ar_decode(p, cfg, o)[0])(big_tp, obs), tokens)
    # a tree block after the prefill: two branches sharing a root
    b = tokens.shape[0]
    block = jnp.concatenate([tokens[:, :3], tokens[:, 1:2] + 1], 1)  # [B, 4]: root, child, grandchild | 2nd child
    depth = jnp.broadcast_to(jnp.array([0, 1, 2, 1]), (b, 4))
    intra = jnp.broadcast_to(jnp.array([[1, 0, 0, 0], [1, 1, 0, 0], [1, 1, 1, 0], [1, 0, 0, 1]], bool), (b, 4, 4))
    outs = []
    for params, c in ((tp, CFG), (big_tp, cfg)):
        _, _, cache = vla.prefill(params, c, obs)
        logits, hidden, blk = vla.cached_pass(params, c, cache, block, depth, intra)
        cache = vla.commit(cache, blk, jnp.zeros((b, 2), jnp.int32).at[:, 1].set(3), jnp.full((b,), 2))
        after, _, _ = vla.cached_pass(params, c, cache, tokens[:, 3:4], jnp.zeros((b, 1), jnp.int32),
                                 jnp.ones((b, 1, 1), bool))
        fused = vla.prefill_with_block(params, c, obs, block, depth, intra)[3]
        outs.append([vla.action_logits(c, y) for y in (logits, after, fused)] + [hidden[..., :CFG.d_model]])
    for small, big in zip(*outs):
        np.testing.assert_allclose(big, small, **TOL)


def test_drafter_and_speculative_decoding_are_exact(expanded, request):
    (tp, dp), (big_tp, big_dp, cfg) = expanded["random"]
    obs = make_obs(5)
    x, hidden, key_ok = drafter.target_sequence(tp, CFG, obs, ar(tp, obs))
    bx, bhidden, bkey_ok = drafter.target_sequence(big_tp, cfg, obs, ar(tp, obs))
    feats = drafter.teacher_forced(dp, CFG, x, hidden, key_ok)
    big_feats = drafter.teacher_forced(big_dp, cfg, bx, bhidden, bkey_ok)
    np.testing.assert_allclose(big_feats[:, cfg.image_pad:, :CFG.d_model], feats, **TOL)
    if request.node.callspec.params["expanded"] != "wide":
        return  # one speculative decode compiles for half a minute on 2 cores: the tree passes are pinned above
    (tp, dp), (big_tp, big_dp, cfg) = expanded["aligned"]  # drafts accepted: trees verified and committed
    spec = sd.SpecConfig(top_k=3, depth=3, total_tokens=8)
    tokens, stats = sd.spec_decode(tp, dp, CFG, spec, obs)
    big_tokens, big_stats = sd.spec_decode(big_tp, big_dp, cfg, spec, obs)
    np.testing.assert_array_equal(big_tokens, tokens)
    np.testing.assert_array_equal(big_tokens, ar(tp, obs))
    np.testing.assert_array_equal(big_stats["target_passes"], stats["target_passes"])  # the same drafts accepted
    assert np.asarray(stats["target_passes"]).max() < 7


def test_layer_layouts_compute_the_same_function(expanded):
    (tp, _), (big_tp, _, cfg) = expanded["random"]
    stacked, stacked_cfg = scale.with_layout(big_tp, cfg, per_layer=False)
    assert cfg.per_layer and not stacked_cfg.per_layer and "blocks" in stacked and "layer0" not in stacked
    obs = make_obs(6)
    np.testing.assert_allclose(vla.prefill(stacked, stacked_cfg, obs)[0], vla.prefill(big_tp, cfg, obs)[0], **TOL)
    back, back_cfg = scale.with_layout(stacked, stacked_cfg, per_layer=True)
    assert back_cfg == cfg and jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.all(a == b)), back, big_tp))


def test_named_scales_are_larger_than_the_shipped_geometry():
    shipped = dataclasses.replace(vla.VLAConfig(n_views=2, mlp_dim=680))
    big = scale.scaled_config(shipped, "llama2-7b")
    assert (big.d_model, big.n_layers, big.n_heads, big.mlp_dim, big.vocab) == (4096, 32, 32, 11008, 32000)
    assert big.prompt_len == 256 + shipped.text_len + 1
    counts = scale.n_params(big)
    assert 6.6e9 < counts["decoder"] < 6.9e9 and 0.55e9 < counts["vision"] < 0.65e9
    assert 0.8e9 < scale.n_params(scale.scaled_config(shipped, "llama-1b"))["decoder"] < 1.2e9


def test_a_scale_the_device_cannot_hold_is_refused_before_any_weight_is_made(monkeypatch):
    shipped = vla.VLAConfig(n_views=2, mlp_dim=680)
    monkeypatch.setattr(scale, "device_bytes", lambda: 8 * 2**30)  # an 8 GiB device
    scale.check_fits(shipped, "llama-1b", "bfloat16")  # ~3 GiB
    with pytest.raises(ValueError, match=r"'llama2-7b' in bfloat16 needs 14\.\d GiB .* valid here: shipped, llama-1b$"):
        scale.check_fits(shipped, "llama2-7b", "bfloat16")


def test_bad_scales_are_refused_with_the_valid_choices():
    with pytest.raises(ValueError, match="unknown target scale 'llama3'; valid: shipped, llama2-7b, llama-1b"):
        scale.scaled_config(CFG, "llama3")
    small = dataclasses.replace(SCALES["wide"], d_model=16, n_heads=2)
    with pytest.raises(ValueError, match=r"smaller than the target \(d_model 16 < 32.*valid: shipped"):
        scale.scaled_config(CFG, small)
    with pytest.raises(ValueError, match="head size 12 is not a multiple of the target's 8"):
        scale.scaled_config(CFG, dataclasses.replace(SCALES["wide"], d_model=48, n_heads=4))
    with pytest.raises(ValueError, match="unknown target_scale 'huge'; valid: shipped, llama2-7b, llama-1b"):
        methods.check_settings("heisd", {"target_scale": "huge"})
