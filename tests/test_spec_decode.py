"""Drafter-based speculative decoding: tree structure, tree verification, acceptance, and
the lossless property of strict acceptance (token-identical to greedy AR)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import acceptance, drafter, spec_decode as sd, vla

from tiny_models import CFG, aligned_pair, ar, obs as make_obs

B = 4


@pytest.fixture(scope="module")
def params():
    return vla.init_params(CFG, jax.random.PRNGKey(0)), drafter.init_params(CFG, jax.random.PRNGKey(1))


_spec_decode = jax.jit(sd.spec_decode, static_argnums=(2, 3))  # compiled once per (spec, batch shape)


def _decode(tp, dp, spec, obs):
    return _spec_decode(tp, dp, CFG, spec, obs)


def test_strict_equals_ar_with_random_parameters(params):
    tp, dp = params
    obs = make_obs()
    tokens, stats = _decode(tp, dp, sd.SpecConfig(top_k=4, depth=3, total_tokens=10), obs)
    np.testing.assert_array_equal(np.asarray(tokens), np.asarray(ar(tp, obs)))
    assert np.all(np.asarray(stats["target_passes"]) <= 7)


@pytest.mark.parametrize("noise,depth", [(0.0, 3), (0.0, 6), (0.35, 4)])
def test_strict_equals_ar_when_drafts_are_accepted(noise, depth):
    tp, dp = aligned_pair(noise)
    obs = make_obs(1, batch=6)
    spec = sd.SpecConfig(top_k=4, depth=depth, total_tokens=4 * depth)
    tokens, stats = _decode(tp, dp, spec, obs)
    np.testing.assert_array_equal(np.asarray(tokens), np.asarray(ar(tp, obs)))
    passes = np.asarray(stats["target_passes"])
    if noise == 0:  # a perfect drafter: prefill + ceil(6 / (depth + 1)) verification passes, unless
        # EAGLE-2's frontier pruned the greedy path (cumulative scores of other branches won)
        ideal = 1 + int(np.ceil(6 / (depth + 1)))
        assert passes.min() == ideal and np.all(passes >= ideal), passes
    else:
        assert np.all((passes >= 2) & (passes <= 7)) and passes.min() < 7, passes


def test_unbatched_equals_batched(params):
    tp, dp = aligned_pair(0.35)
    obs = make_obs(2)
    spec = sd.SpecConfig(top_k=4, depth=3, total_tokens=12, acceptance="token_relaxed", relax_bins=9)
    tokens, stats = _decode(tp, dp, spec, obs)
    for i in range(B):
        one = jax.tree.map(lambda x: x[i: i + 1], obs)
        t1, s1 = _decode(tp, dp, spec, one)
        np.testing.assert_array_equal(np.asarray(t1[0]), np.asarray(tokens[i]))
        assert float(s1["target_passes"][0]) == float(stats["target_passes"][i])


def test_relaxed_acceptance_keeps_drafts_within_r_bins():
    spec = sd.SpecConfig(acceptance="token_relaxed", relax_bins=3)
    draft, target = jnp.array([10, 10, 10, 10, 0]), jnp.array([10, 13, 14, 7, 255])
    np.testing.assert_array_equal(np.asarray(acceptance.token_accepted(spec.acceptance, spec.relax_bins, draft, target)), [True, True, False, True, False])
    np.testing.assert_array_equal(np.asarray(acceptance.token_accepted("strict", 0, draft, target)), [True, False, False, False, False])


def _assert_within_r_of_the_target(spec):
    """Each token relaxed decoding emits is within relax_bins of the target's greedy token
    given the emitted prefix (checked by teacher forcing the target on the output)."""
    tp, dp = aligned_pair(0.35)
    obs = make_obs(3)
    tokens, _ = _decode(tp, dp, spec, obs)
    logits, _ = vla.forward(tp, CFG, obs, tokens)
    p = CFG.prompt_len
    greedy = np.asarray(jnp.argmax(vla.action_logits(CFG, logits[:, p - 1: p + 6]), -1))
    assert np.all(np.abs(np.asarray(tokens) - CFG.first_action_id - greedy) <= spec.relax_bins)


def test_relaxed_tokens_stay_within_r_of_the_target_greedy_choice():
    _assert_within_r_of_the_target(sd.SpecConfig(top_k=4, depth=4, total_tokens=16, acceptance="token_relaxed",
                                                 relax_bins=6))


def _first_tree(params, spec):
    """The draft tree below the first action token of a prefilled prompt."""
    tp, dp = params
    obs = make_obs()
    _, hidden, x, _ = vla.prefill_features(tp, CFG, obs)
    feat, dcache = drafter.prompt_pass(dp, CFG, x, hidden, vla.prompt_key_mask(CFG, obs.instruction),
                                       vla.embed_tokens(tp, jnp.full((B,), CFG.first_action_id)))
    return sd.draft_tree(dp, tp, CFG, spec, dcache, feat)


def test_tree_structure_and_selection_keep_ancestors(params):
    spec = sd.SpecConfig(top_k=3, depth=4, total_tokens=7)
    tree = _first_tree(params, spec)
    anc, parent, score = map(np.asarray, (tree.anc, tree.parent, tree.score))
    m = spec.top_k * spec.depth
    for b in range(B):
        for g in range(m):
            expect = np.zeros(m, bool)
            expect[g] = True
            if parent[b, g] >= 0:
                expect |= anc[b, parent[b, g]]
                assert score[b, g] <= score[b, parent[b, g]]
                assert np.asarray(tree.depth)[parent[b, g]] == np.asarray(tree.depth)[g] - 1
            np.testing.assert_array_equal(anc[b, g], expect)
    sel = np.asarray(sd.select_nodes(tree, spec.total_tokens))
    for b in range(B):
        chosen = set(sel[b].tolist())
        assert all(set(np.flatnonzero(anc[b, g]).tolist()) <= chosen for g in chosen)


def test_tree_verification_equals_sequential_decoding_of_each_path(params):
    tp, dp = params
    obs = make_obs(5)
    logits, hidden, x, cache = vla.prefill_features(tp, CFG, obs)
    root = jnp.argmax(vla.action_logits(CFG, logits), -1) + CFG.first_action_id
    feat, dcache = drafter.prompt_pass(dp, CFG, x, hidden, vla.prompt_key_mask(CFG, obs.instruction),
                                       vla.embed_tokens(tp, root))
    spec = sd.SpecConfig(top_k=2, depth=3, total_tokens=6)
    tree = sd.draft_tree(dp, tp, CFG, spec, dcache, feat)
    sel = sd.select_nodes(tree, spec.total_tokens)
    block, depth, intra = sd.tree_block(CFG, root, tree, sel)
    tree_logits, _, _ = vla.cached_pass(tp, CFG, cache, block, depth, intra)
    one = jnp.ones((B, 1, 1), bool)
    zero = jnp.zeros((B, 1), jnp.int32)
    step = jax.jit(lambda c, t: vla.cached_pass(tp, CFG, c, t, zero, one))
    commit = jax.jit(lambda c, kv: vla.commit(c, kv, zero, jnp.ones((B,), jnp.int32)))
    intra, tree_logits = np.asarray(intra), np.asarray(tree_logits)
    for n in range(1, block.shape[1]):  # node n: decode root + row b's path one token at a time
        for b in range(B):  # rows draft different trees: each row's own path
            path = [0] + [j for j in range(1, block.shape[1]) if intra[b, n, j]]
            c = cache
            for j in path:  # the whole batch fed block[:, j]; only row b's result is read
                lg, _, kv = step(c, block[:, j:j + 1])
                c = commit(c, kv)
            np.testing.assert_allclose(np.asarray(lg[b, 0]), tree_logits[b, n], atol=2e-4, err_msg=f"row {b} node {n}")


def test_cache_after_commit_equals_one_by_one_decoding():
    tp, dp = aligned_pair(0.0)
    obs = make_obs(6)
    spec = sd.SpecConfig(top_k=4, depth=3, total_tokens=12)
    logits, hidden, x, cache = vla.prefill_features(tp, CFG, obs)
    root = jnp.argmax(vla.action_logits(CFG, logits), -1) + CFG.first_action_id
    feat, dcache = drafter.prompt_pass(dp, CFG, x, hidden, vla.prompt_key_mask(CFG, obs.instruction),
                                       vla.embed_tokens(tp, root))
    tree = sd.draft_tree(dp, tp, CFG, spec, dcache, feat)
    v = sd.verify(tp, CFG, spec, cache, root, tree, sd.select_nodes(tree, spec.total_tokens))
    n_acc = np.asarray(v.n_accepted)
    assert n_acc.max() > 0
    one = jnp.ones((B, 1, 1), bool)
    zero = jnp.zeros((B, 1), jnp.int32)
    step = jax.jit(lambda c, t: vla.commit(c, vla.cached_pass(tp, CFG, c, t, zero, one)[2], zero, jnp.ones((B,), jnp.int32)))
    for b in range(B):
        toks = [int(root[b])] + [int(t) for t in np.asarray(v.tokens[b, :n_acc[b]])]
        c = cache
        for t in toks:  # one token at a time into a cache of its own (the whole batch fed row b's token)
            c = step(c, jnp.full((B, 1), t))
        n = CFG.prompt_len + len(toks)
        assert int(v.cache.length[b]) == n
        np.testing.assert_allclose(np.asarray(v.cache.k[:, b, :n]), np.asarray(c.k[:, b, :n]), atol=2e-5)
        np.testing.assert_allclose(np.asarray(v.cache.v[:, b, :n]), np.asarray(c.v[:, b, :n]), atol=2e-5)
        np.testing.assert_array_equal(np.asarray(v.cache.key_mask[b]), np.asarray(c.key_mask[b]))


def test_spec_config_rejects_bad_settings():
    with pytest.raises(ValueError, match="valid: strict, token_relaxed"):
        sd.SpecConfig(acceptance="loose")
    with pytest.raises(ValueError, match="total_tokens"):
        sd.SpecConfig(top_k=2, depth=2, total_tokens=5)
    with pytest.raises(ValueError, match="cache slots"):
        sd.SpecConfig(top_k=16, depth=8, total_tokens=50).check_fits(CFG)
    with pytest.raises(ValueError, match="spread draft trees are for token_relaxed"):
        sd.SpecConfig(spread=True)


def test_spread_children_cover_disjoint_acceptance_windows():
    r, k = 3, 4
    p = np.full(256, 1e-6)
    p[100:104] = [0.3, 0.25, 0.2, 0.05]  # one peak (as EAGLE's top-k would pick 100, 101, 102, 103)
    p[30] = 0.1
    p[200] = 0.09
    logp = jnp.log(jnp.asarray(p / p.sum(), jnp.float32))[None]
    score, bins = map(np.asarray, sd.spread_children(logp, k, r))
    window = np.convolve(p / p.sum(), np.ones(2 * r + 1), mode="same")
    assert window[bins[0, 0]] == pytest.approx(window.max(), rel=1e-3)  # the bin whose +-r window holds the most mass
    assert bins[0, 0] in (100, 101)  # ... among equal windows, centred nearest the mode
    np.testing.assert_allclose(score[0], np.log(window[bins[0]]), rtol=1e-5)
    assert sorted(bins[0, 1:3].tolist()) == [30, 200]  # the other modes, not the peak's neighbours
    assert all(abs(a - b) > 2 * r for i, a in enumerate(bins[0]) for b in bins[0, i + 1:])
    assert np.all(np.diff(score[0]) <= 0)
    # Fewer disjoint windows than children: the rest score -inf (never chosen over a real node).
    wide, _ = sd.spread_children(logp, 12, 12)
    assert np.isneginf(np.asarray(wide)[0, -2:]).all() and np.isfinite(np.asarray(wide)[0, :10]).all()


def test_spread_tree_levels_keep_their_children_apart(params):
    r = 5
    spec = sd.SpecConfig(top_k=3, depth=3, total_tokens=9, acceptance="token_relaxed", relax_bins=r, spread=True)
    tree = _first_tree(params, spec)
    bins, parent = np.asarray(tree.bins), np.asarray(tree.parent)
    for b in range(B):
        for level in range(spec.depth):
            nodes = range(level * spec.top_k, (level + 1) * spec.top_k)
            for g in nodes:  # siblings (same parent) are more than 2r bins apart
                for h in nodes:
                    if g < h and parent[b, g] == parent[b, h]:
                        assert abs(int(bins[b, g]) - int(bins[b, h])) > 2 * r
    _assert_within_r_of_the_target(spec)  # relaxed decoding with spread trees
