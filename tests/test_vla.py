"""The VLA's KV cache and decoding: cached == uncached, batched == per-example, commit."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import target_model, vla

CFG = vla.VLAConfig(image_size=16, patch_size=8, vision_layers=1, d_model=32, n_layers=2, n_heads=4, mlp_dim=64,
                    cache_slots=48)
B = 3


def _obs(seed=0, b=B):
    rng = np.random.default_rng(seed)
    instr = np.zeros((b, CFG.text_len), np.int32)
    for i in range(b):  # different instruction lengths: different padding per row
        n = 4 + 2 * i
        instr[i, : n + 2] = np.r_[1, rng.integers(4, CFG.text_vocab, n), 2]
    return vla.Observation(image=jnp.asarray(rng.integers(0, 255, (b, 16, 16, 3)), jnp.uint8),
                           instruction=jnp.asarray(instr), proprio=jnp.asarray(rng.normal(size=(b, 8)), jnp.float32))


@pytest.fixture(scope="module")
def model():
    params = vla.init_params(CFG, jax.random.PRNGKey(0))
    # Sharpen the random model so greedy tokens are not ties.
    params = jax.tree.map(lambda x: x * 3.0, params)
    fns = dict(
        forward=jax.jit(lambda p, o, t: vla.forward(p, CFG, o, t)),
        prefill=jax.jit(lambda p, o: vla.prefill(p, CFG, o)),
        decode=jax.jit(lambda p, c, t, d, m: vla.cached_pass(p, CFG, c, t, d, m)),
        ar=jax.jit(lambda p, o: target_model.ar_decode(p, CFG, o)[0]),
    )
    return params, fns


def test_ar_decoding_with_cache_matches_full_forward_logits(model):
    params, f = model
    obs = _obs()
    toks = f["ar"](params, obs)
    assert toks.shape == (B, 7)
    assert np.all((toks >= CFG.first_action_id) & (toks < CFG.vocab_size))
    full, _ = f["forward"](params, obs, toks)
    p = CFG.prompt_len
    # Prefill logits == uncached logits at the last prompt position.
    lg, _, cache = f["prefill"](params, obs)
    # Logits reach |20| in float32 and the cached and uncached passes sum in different orders:
    # they differ by up to 2e-4 (jax 0.10.2 on a 2-core CPU); a cache bug is off by O(1).
    tol = 5e-4
    np.testing.assert_allclose(lg, full[:, p - 1], atol=tol)
    # Each cached single-token decode == uncached logits at that position.
    for i in range(6):
        lg, _, blk = f["decode"](params, cache, toks[:, i:i + 1], jnp.zeros((B, 1), jnp.int32), jnp.ones((B, 1, 1), bool))
        cache = vla.commit(cache, blk, jnp.zeros((B, 1), jnp.int32), jnp.ones((B,), jnp.int32))
        np.testing.assert_allclose(lg[:, 0], full[:, p + i], atol=tol)
    # Greedy tokens are what the full forward predicts.
    pred = jnp.argmax(vla.action_logits(CFG, full[:, p - 1:p + 6]), -1) + CFG.first_action_id
    np.testing.assert_array_equal(pred, toks)


def test_batched_decoding_equals_per_example(model):
    params, f = model
    obs = _obs(1)
    toks = f["ar"](params, obs)
    for i in range(B):
        one = jax.tree.map(lambda x: jnp.repeat(x[i:i + 1], B, 0), obs)  # same compiled shape
        np.testing.assert_array_equal(f["ar"](params, one)[0], toks[i])


def test_multi_token_block_and_commit_equal_sequential_decoding(model):
    params, f = model
    obs = _obs(2)
    toks = f["ar"](params, obs)
    full, _ = f["forward"](params, obs, toks)
    p = CFG.prompt_len
    _, _, cache = f["prefill"](params, obs)
    # Decode 3 tokens at once with a causal mask: logits equal the uncached ones.
    causal = jnp.broadcast_to(jnp.tril(jnp.ones((3, 3), bool)), (B, 3, 3))
    lg, _, blk3 = f["decode"](params, cache, toks[:, :3], jnp.broadcast_to(jnp.arange(3), (B, 3)), causal)
    np.testing.assert_allclose(lg, full[:, p:p + 3], atol=1e-4)
    # Rows keep different numbers of them; the next token then sees exactly those.
    n = jnp.array([1, 2, 3])
    c = vla.commit(cache, blk3, jnp.broadcast_to(jnp.arange(3), (B, 3)), n)
    np.testing.assert_array_equal(c.length, p + n)
    nxt = toks[jnp.arange(B), n][:, None]
    lg, _, _ = f["decode"](params, c, nxt, jnp.zeros((B, 1), jnp.int32), jnp.ones((B, 1, 1), bool))
    for i in range(B):
        np.testing.assert_allclose(lg[i, 0], full[i, p + int(n[i])], atol=1e-4)


def test_commit_moves_the_chosen_tokens_into_place(model):
    params, f = model
    obs = _obs(3)
    toks = f["ar"](params, obs)
    _, _, cache = f["prefill"](params, obs)
    # Decode tokens [t0, x, t1] as a "tree" where node 2 hangs off node 0, keep nodes 0 and 2.
    junk = jnp.full((B, 1), CFG.first_action_id)
    block = jnp.concatenate([toks[:, :1], junk, toks[:, 1:2]], 1)
    depth = jnp.broadcast_to(jnp.array([0, 1, 1]), (B, 3))
    tree = jnp.broadcast_to(jnp.array([[1, 0, 0], [1, 1, 0], [1, 0, 1]], bool), (B, 3, 3))
    _, _, blk = f["decode"](params, cache, block, depth, tree)
    c = vla.commit(cache, blk, jnp.broadcast_to(jnp.array([0, 2]), (B, 2)), jnp.full((B,), 2))
    # The cache now equals one that decoded t0, t1 one by one.
    _, _, blk = f["decode"](params, cache, toks[:, :2], jnp.broadcast_to(jnp.arange(2), (B, 2)),
                            jnp.broadcast_to(jnp.tril(jnp.ones((2, 2), bool)), (B, 2, 2)))
    ref = vla.commit(cache, blk, jnp.broadcast_to(jnp.arange(2), (B, 2)), jnp.full((B,), 2))
    np.testing.assert_array_equal(c.length, ref.length)
    np.testing.assert_array_equal(c.key_mask, ref.key_mask)
    live = np.asarray(ref.key_mask)[None, :, :, None, None]
    np.testing.assert_allclose(np.where(live, c.k, 0), np.where(live, ref.k, 0), atol=1e-5)
    np.testing.assert_allclose(np.where(live, c.v, 0), np.where(live, ref.v, 0), atol=1e-5)


def test_config_rejects_bad_shapes():
    with pytest.raises(ValueError, match="multiple of patch_size"):
        vla.VLAConfig(image_size=30, patch_size=8)
    with pytest.raises(ValueError, match="cache_slots"):
        vla.VLAConfig(cache_slots=20)


def test_fused_attention_is_refused_where_it_cannot_run():
    with pytest.raises(ValueError, match="attention 'flash': valid are xla, cudnn"):
        vla.VLAConfig(attention="flash")
    with pytest.raises(ValueError, match="not float32; valid for float32: xla"):
        vla.VLAConfig(attention="cudnn", dtype="float32")
    assert "attention" not in vla.VLAConfig().architecture()  # numerics: a checkpoint serves either
    if jax.default_backend() != "gpu":
        cfg = vla.VLAConfig(image_size=16, d_model=32, n_heads=2, n_layers=1, attention="cudnn", dtype="bfloat16")
        with pytest.raises(ValueError, match="runs on a GPU"):
            vla.init_params(cfg, jax.random.PRNGKey(0))


def test_auto_attention_fuses_only_a_large_16_bit_model_on_a_gpu():
    big = vla.VLAConfig(image_size=16, d_model=32, n_heads=2, n_layers=1, dtype="bfloat16", per_layer=True)
    assert vla.resolve_attention("auto", big, backend="gpu") == "cudnn"
    for other, backend in ((big, "cpu"), (dataclasses.replace(big, dtype="float32"), "gpu"),
                           (dataclasses.replace(big, per_layer=False), "gpu"),
                           (dataclasses.replace(big, matmul_precision="bf16_invariant"), "gpu")):
        assert vla.resolve_attention("auto", other, backend=backend) == "xla", (other, backend)
    # a named attention is kept as given (VLAConfig refuses what cannot compute)
    assert vla.resolve_attention("xla", big, backend="gpu") == "xla"
    assert vla.resolve_attention("cudnn", big, backend="cpu") == "cudnn"


def test_dense_patchify_is_the_convolution():
    # One function, one parameter tree: a checkpoint serves either form, and the prefill's logits
    # agree to rounding (on a CPU, bit for bit) over two tiled views in float32 and bfloat16.
    conv = vla.VLAConfig(image_size=16, patch_size=8, n_views=2, vision_layers=1, d_model=32, n_layers=2, n_heads=4,
                         mlp_dim=64)
    dense = dataclasses.replace(conv, patchify="dense")
    params = vla.init_params(conv, jax.random.PRNGKey(1))
    twin = vla.init_params(dense, jax.random.PRNGKey(1))
    assert jax.tree.structure(params) == jax.tree.structure(twin)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(twin)):
        np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(3)
    obs = dataclasses.replace(_obs(), image=jnp.asarray(rng.integers(0, 255, (B, *conv.image_shape)), jnp.uint8))
    for dtype, tol in (("float32", 1e-5), ("bfloat16", 0.1)):
        p = jax.tree.map(lambda x: x.astype(dtype), params)
        want = vla.prefill(p, dataclasses.replace(conv, dtype=dtype), obs)[0].astype(jnp.float32)
        got = vla.prefill(p, dataclasses.replace(dense, dtype=dtype), obs)[0].astype(jnp.float32)
        np.testing.assert_allclose(got, want, atol=tol)
    with pytest.raises(ValueError, match="patchify 'im2col': valid are conv, dense"):
        vla.VLAConfig(patchify="im2col")
    assert "patchify" not in vla.VLAConfig().architecture()  # numerics: not a checkpoint's


def test_tiled_views_give_one_patch_grid_per_view():
    one, two = vla.VLAConfig(image_size=16, patch_size=8), vla.VLAConfig(image_size=16, patch_size=8, n_views=2)
    assert two.image_shape == (16, 32, 3) and two.n_patches == 2 * one.n_patches
    assert two.prompt_len == one.prompt_len + one.n_patches
    assert two.cache_slots - two.prompt_len == one.cache_slots - one.prompt_len == vla.DRAFT_SLOTS
    with pytest.raises(ValueError, match="n_views"):
        vla.VLAConfig(n_views=0)


def test_random_shift_moves_each_view_on_its_own():
    from heisd_jax.harness import data

    img = np.zeros((4, 8, 16, 3), np.uint8)
    img[:, :, 8:] = 255  # view 0 black, view 1 white
    out = np.asarray(data.random_shift(jnp.asarray(img), jax.random.PRNGKey(0), 3, n_views=2))
    assert (out[:, :, :8] == 0).all() and (out[:, :, 8:] == 255).all()  # no view bleeds into the other
    whole = np.asarray(data.random_shift(jnp.asarray(img), jax.random.PRNGKey(0), 3))
    assert not ((whole[:, :, :8] == 0).all() and (whole[:, :, 8:] == 255).all())


def test_training_forward_is_the_inference_forward(model):
    """The training variant (unrolled layers) computes the same logits and hidden states as
    the forward the decoding API is pinned to."""
    params, f = model
    obs = _obs(1)
    toks = jnp.full((B, 7), CFG.first_action_id + 5, jnp.int32)
    ref_logits, ref_hidden = f["forward"](params, obs, toks)
    logits, hidden = jax.jit(lambda p, o, t: vla.forward(p, CFG, o, t, training=True))(params, obs, toks)
    np.testing.assert_allclose(logits, ref_logits, atol=1e-4)
    np.testing.assert_allclose(hidden, ref_hidden, atol=1e-4)
    # The head at the positions from `logits_from` on only (the training loss reads the action
    # positions): those positions' logits, the same hidden states.
    start = CFG.prompt_len - 1
    tail, hidden = jax.jit(lambda p, o, t: vla.forward(p, CFG, o, t, training=True, logits_from=start))(params, obs, toks)
    assert tail.shape == (B, 8, CFG.vocab_size)
    np.testing.assert_allclose(tail, ref_logits[:, start:], atol=1e-4)
    np.testing.assert_allclose(hidden, ref_hidden, atol=1e-4)


def test_unrolled_inference_decodes_the_same_tokens(model):
    """`VLAConfig.unroll` (straight-line passes, AR's token loop included) is the same
    function as the scanned decode: same greedy tokens, same prompt logits."""
    params, f = model
    obs = _obs(1)
    cfg = dataclasses.replace(CFG, unroll=True)
    np.testing.assert_array_equal(jax.jit(lambda p, o: target_model.ar_decode(p, cfg, o)[0])(params, obs), f["ar"](params, obs))
    np.testing.assert_allclose(jax.jit(lambda p, o: vla.prefill(p, cfg, o)[0])(params, obs),
                               f["prefill"](params, obs)[0], atol=1e-4)
