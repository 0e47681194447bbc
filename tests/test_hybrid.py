"""The HeiSD decode step: verification fused into the prefill, lossless strict mode with
retrieval drafts (token-identical to AR, batched, rows accepting different lengths),
verify-skip and the step's state (tiny random models on CPU)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import acceptance, budget, hybrid, kinematics, retrieval, spec_decode as sd, vla
from heisd_jax.tokenizer import ActionTokenizer

from tiny_models import CFG, HYBRID_B as B, candidates

SPEC = sd.SpecConfig(top_k=2, depth=2, total_tokens=4)
STRICT = dataclasses.replace(hybrid.PAPER, spec=SPEC, mode="retrieval", acceptance="strict", n_candidates=3,
                             skip=acceptance.SkipConfig(enabled=False))


_decode = jax.jit(hybrid.decode, static_argnums=(1, 2))


def test_prefill_with_block_equals_prefill_then_decode(tiny_hybrid):
    params, obs, ar_tokens = tiny_hybrid
    tp = params["target"]
    cand, _ = candidates(ar_tokens, np.random.default_rng(0))
    block = hybrid.candidate_block(cand)
    lg, h, x, blg, bh, cache, kv = vla.prefill_with_block(tp, CFG, obs, *block)
    lg2, h2, x2, cache2 = vla.prefill_features(tp, CFG, obs)
    blg2, bh2, kv2 = vla.cached_pass(tp, CFG, cache2, *block)
    np.testing.assert_allclose(np.asarray(lg), np.asarray(lg2), atol=2e-4)
    np.testing.assert_allclose(np.asarray(blg), np.asarray(blg2), atol=2e-4)
    for mine, ref in ((cache.k, cache2.k), (kv.k, kv2.k), (kv.v, kv2.v)):
        np.testing.assert_allclose(np.asarray(mine), np.asarray(ref), atol=2e-5)
    np.testing.assert_array_equal(np.asarray(cache.length), np.asarray(cache2.length))
    np.testing.assert_array_equal(np.asarray(cache.key_mask), np.asarray(cache2.key_mask))


@pytest.mark.parametrize("verify,continuation", [("prefill", "drafter"), ("separate", "drafter"), ("prefill", "ar")])
def test_strict_hybrid_equals_ar_token_for_token(tiny_hybrid, verify, continuation):
    params, obs, ar_tokens = tiny_hybrid
    cand, cuts = candidates(ar_tokens, np.random.default_rng(1))
    hcfg = dataclasses.replace(STRICT, verify=verify, continuation=continuation)
    assert hcfg.lossless
    use = jnp.array([True, True, True, True, False, True])
    valid = jnp.ones((B, 3), bool).at[5, 1].set(False)  # row 5's exact candidate is masked out
    tokens, stats = _decode(params, CFG, hcfg, obs, cand, valid, use, jnp.zeros((B,), bool))
    np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
    acc = np.asarray(stats["retrieval_accepted"])
    expect = np.where(np.asarray(use) & np.asarray(valid[:, 1]), cuts, 0)
    assert np.all(acc >= expect) and acc[0] == 7, (acc, expect)  # random candidates may add a lucky token
    passes = np.asarray(stats["target_passes"])
    assert passes[0] == (1 if verify == "prefill" else 2)  # a whole action verified in one pass
    assert np.all(passes <= 7 + (verify == "separate"))
    if continuation == "ar":  # one pass per token the candidates did not give; the drafter never runs
        np.testing.assert_array_equal(passes, 1 + np.maximum(6 - acc, 0))
        np.testing.assert_array_equal(np.asarray(stats["drafter_passes"]), 0)


def test_skipped_rows_execute_the_top_candidate_without_a_target_pass(tiny_hybrid):
    params, obs, ar_tokens = tiny_hybrid
    cand, _ = candidates(ar_tokens, np.random.default_rng(2))
    hcfg = dataclasses.replace(STRICT, acceptance="seq_relaxed", skip=hybrid.PAPER.skip)
    use = jnp.ones((B,), bool)
    skip = jnp.array([True, False, True, False, False, False])
    valid = jnp.ones((B, 3), bool)
    tokens, stats = _decode(params, CFG, hcfg, obs, cand, valid, use, skip)
    np.testing.assert_array_equal(np.asarray(tokens)[[0, 2]], np.asarray(cand)[[0, 2], 0])
    np.testing.assert_array_equal(np.asarray(stats["target_passes"])[[0, 2]], 0)
    assert np.all(np.asarray(stats["target_passes"])[[1, 3, 4, 5]] >= 1)
    all_skip, st = _decode(params, CFG, hcfg, obs, cand, valid, use, jnp.ones((B,), bool))  # no target call
    np.testing.assert_array_equal(np.asarray(all_skip), np.asarray(cand)[:, 0])
    assert float(jnp.sum(st["target_passes"])) == 0 and float(jnp.sum(st["skipped"])) == B


def test_strict_trees_after_relaxed_candidates_equal_the_ar_continuation(tiny_hybrid):
    """Candidates accepted sequence-wise relaxed, then strict drafter trees: every token after
    the accepted prefix is the target's own given that prefix, as continuation=ar's
    single-token passes give it, so both decode the same actions (the guard's actions,
    decoded in draft rounds instead of one pass per token)."""
    params, obs, ar_tokens = tiny_hybrid
    cand, cuts = candidates(ar_tokens, np.random.default_rng(2))
    near = np.array(cand)
    lo, hi = CFG.first_action_id, CFG.first_action_id + 255
    for b, cut in enumerate(cuts):  # 3 bins off AR's up to the cut: accepted relaxed, not strict
        near[b, 1, :cut] = np.clip(ar_tokens[b, :cut] + 3, lo, hi)
    near = jnp.asarray(near)
    use, valid, no_skip = jnp.ones((B,), bool), jnp.ones((B, 3), bool), jnp.zeros((B,), bool)
    trees = dataclasses.replace(STRICT, acceptance="seq_relaxed")
    assert trees.spec.acceptance == "strict" and trees.continuation == "drafter"
    tokens, stats = _decode(params, CFG, trees, obs, near, valid, use, no_skip)
    ar_tokens_cont, ar_stats = _decode(params, CFG, dataclasses.replace(trees, continuation="ar"), obs, near, valid,
                                       use, no_skip)
    np.testing.assert_array_equal(np.asarray(tokens), np.asarray(ar_tokens_cont))
    assert (np.asarray(tokens) != ar_tokens).any()  # the relaxed prefixes were taken: not AR's actions
    assert np.asarray(stats["drafter_passes"]).sum() > 0  # the trees ran
    assert np.asarray(ar_stats["drafter_passes"]).sum() == 0


def test_step_never_exceeds_k_skip_and_strict_step_equals_ar(tiny_hybrid):
    """A datastore holding each row's AR action under its own key: retrieval is perfect, so
    skipping would fire every step; it must stop after k_skip in a row, and only while in
    the retrieval mode. With strict acceptance and skip off, the step's tokens are AR's."""
    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    state = hybrid.init_state(B, spec)
    keys = retrieval.make_keys(spec, tok, state.prev_actions, obs.proprio)
    store = retrieval.Datastore(keys=jnp.repeat(keys, 3, 0), sq_norms=jnp.repeat((keys * keys).sum(-1), 3),
                                tokens=jnp.repeat(jnp.asarray(ar_tokens), 3, 0), task=jnp.repeat(jnp.arange(B), 3))
    p = dict(params, store=store)
    kin = hybrid.Kinematics(lin_vel=jnp.zeros((B, 3)), ang_vel=jnp.zeros((B, 3)), lin_acc=jnp.zeros((B, 3)),
                            gripper_vel=jnp.zeros((B,)))
    hcfg = dataclasses.replace(hybrid.PAPER, spec=SPEC, mode="hybrid", acceptance="seq_relaxed", n_candidates=3,
                               skip=acceptance.SkipConfig(source="retrieval", eps=1e-3, k_skip=2),
                               boundary=kinematics.BoundaryConfig(tau_on=1.0, tau_off=0.5, min_dwell=1))
    run = jax.jit(hybrid.step, static_argnums=(1, 2, 3, 4))
    state = dataclasses.replace(state, boundary=kinematics.boundary_init((B,), kinematics.RETRIEVAL))
    frozen = dataclasses.replace(state)
    skipped, modes = [], []
    for t in range(7):
        # keep the history fixed so the key keeps matching; drafter mode (metric high) at t = 5
        fast = jnp.full((B, 3), 3.0 if t == 5 else 0.0)
        _, tokens, state, stats = run(p, CFG, hcfg, spec, tok, state, obs, dataclasses.replace(kin, lin_vel=fast),
                                      jnp.arange(B))
        state = dataclasses.replace(state, prev_actions=frozen.prev_actions, prev_lin_vel=jnp.zeros((B, 3)))
        skipped.append(np.asarray(stats["skipped"]))
        modes.append(np.asarray(state.boundary.mode))
        np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
    skipped, modes = np.array(skipped), np.array(modes)
    assert skipped[1:3].all() and not skipped[0].any() and not skipped[3].any()  # verify, 2 skips, verify
    assert not skipped[modes == kinematics.DRAFTER].any() and not skipped[5].any()
    lossless = dataclasses.replace(hcfg, acceptance="strict", skip=acceptance.SkipConfig(enabled=False),
                                   spec=sd.SpecConfig(top_k=2, depth=2, total_tokens=4))
    _, tokens, _, stats = run(p, CFG, lossless, spec, tok, hybrid.init_state(B, spec), obs, kin, jnp.arange(B))
    np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)


def test_recent_actions_are_verified_as_candidates(tiny_hybrid):
    """The env's own last executed actions join the datastore's candidates: on an unchanged
    observation the previous action is the target's again, so it is accepted whole in the
    one fused pass (strict: still AR's tokens); the state keeps them newest first."""
    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    rng = np.random.default_rng(3)
    wrong = jnp.asarray(rng.integers(CFG.first_action_id, CFG.first_action_id + 256, (B, 7)), jnp.int32)
    store = retrieval.Datastore(keys=jnp.zeros((B, spec.dim)), sq_norms=jnp.zeros((B,)), tokens=wrong,
                                task=jnp.arange(B))
    p = dict(params, store=store)
    kin = hybrid.Kinematics(lin_vel=jnp.zeros((B, 3)), ang_vel=jnp.zeros((B, 3)), lin_acc=jnp.zeros((B, 3)),
                            gripper_vel=jnp.zeros((B,)))
    hcfg = dataclasses.replace(STRICT, n_candidates=1, recent_candidates=2)
    assert hcfg.lossless and hcfg.n_verified == 3
    run = jax.jit(hybrid.step, static_argnums=(1, 2, 3, 4))
    state = hybrid.init_state(B, spec, hcfg)
    with pytest.raises(ValueError, match="recent actions"):
        run(p, CFG, hcfg, spec, tok, hybrid.init_state(B, spec), obs, kin, jnp.arange(B))
    whole = []
    for t in range(3):
        _, tokens, state, stats = run(p, CFG, hcfg, spec, tok, state, obs, kin, jnp.arange(B))
        np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
        np.testing.assert_array_equal(np.asarray(state.recent[:, 0]), ar_tokens)
        np.testing.assert_array_equal(np.asarray(state.recent_valid), np.arange(2)[None].repeat(B, 0) <= t)
        whole.append(np.asarray(stats["retrieval_whole"]))
    assert not whole[0].all() and whole[1].all() and whole[2].all()
    np.testing.assert_array_equal(np.asarray(stats["target_passes"]), 1)
    # The recent actions alone, AR after them: no datastore query (no store in params at all).
    alone = dataclasses.replace(hcfg, n_candidates=0, continuation="ar")
    state = hybrid.init_state(B, spec, alone)
    for t in range(2):
        _, tokens, state, stats = run(params, CFG, alone, spec, tok, state, obs, kin, jnp.arange(B))
        np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
        np.testing.assert_array_equal(np.asarray(stats["target_passes"]), 7 if t == 0 else 1)
    with pytest.raises(ValueError, match="n_candidates \\+ recent_candidates must be <= 12"):
        dataclasses.replace(hcfg, recent_candidates=12).check_fits(vla.VLAConfig(cache_slots=160))


def test_repeat_skip_executes_the_last_action_after_confirmed_repeats(tiny_hybrid):
    """Verify-skip from recent actions: on an unchanged observation the target repeats its
    action, so once a verified step has accepted the previous action whole (n_confirm 1), the
    next k_skip steps execute it again with no target pass, then one step verifies again."""
    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    kin = hybrid.Kinematics(lin_vel=jnp.zeros((B, 3)), ang_vel=jnp.zeros((B, 3)), lin_acc=jnp.zeros((B, 3)),
                            gripper_vel=jnp.zeros((B,)))
    hcfg = dataclasses.replace(STRICT, acceptance="seq_relaxed", n_candidates=0, recent_candidates=2,
                               continuation="ar", skip=acceptance.SkipConfig(source="recent", n_confirm=1, k_skip=2))
    run = jax.jit(hybrid.step, static_argnums=(1, 2, 3, 4))
    state = hybrid.init_state(B, spec, hcfg)
    skipped, passes = [], []
    for _ in range(7):
        _, tokens, state, stats = run(params, CFG, hcfg, spec, tok, state, obs, kin, jnp.arange(B))
        np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
        skipped.append(np.asarray(stats["skipped"]))
        passes.append(np.asarray(stats["target_passes"]))
    np.testing.assert_array_equal(np.array(skipped), np.array([[0, 0, 1, 1, 0, 1, 1]] * B).T)
    np.testing.assert_array_equal(np.array(passes)[np.array(skipped) > 0], 0)
    np.testing.assert_array_equal(np.array(passes)[[1, 4]], 1)  # the repeat verified in the prefill
    with pytest.raises(ValueError, match="needs recent_candidates >= 1"):
        dataclasses.replace(hcfg, n_candidates=1, recent_candidates=0)


def test_repeat_bounds_confirm_a_loose_repeat_while_executing_the_target_action(tiny_hybrid):
    """SkipConfig.repeat_r_max / repeat_r_seq: with acceptance as tight as strict (r_max 0),
    a last action one bin off the target's is not executed (the target's is), and without
    repeat bounds that step is no repeat, so the skip waits for an exact one; with bounds of
    2 / 6 the same step counts as a repeat and the next step skips, executing the target's
    action again."""
    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    kin = hybrid.Kinematics(lin_vel=jnp.zeros((B, 3)), ang_vel=jnp.zeros((B, 3)), lin_acc=jnp.zeros((B, 3)),
                            gripper_vel=jnp.zeros((B,)))
    last_bin = ar_tokens[:, -1] - CFG.first_action_id  # one bin off, on the gripper's side of the threshold
    off = ar_tokens.copy()
    off[:, -1] += np.where(np.isin(last_bin, (127, 255)), -1, 1)
    skipped = {}
    for bounds in ((None, None), (2, 6)):
        hcfg = dataclasses.replace(
            STRICT, acceptance="seq_relaxed", seq=acceptance.SeqRelaxedConfig(r_max=0, r_seq=0), n_candidates=0,
            recent_candidates=1, continuation="ar",
            skip=acceptance.SkipConfig(source="recent", n_confirm=1, k_skip=1, repeat_r_max=bounds[0],
                                       repeat_r_seq=bounds[1]))
        run = jax.jit(hybrid.step, static_argnums=(1, 2, 3, 4))
        state = dataclasses.replace(hybrid.init_state(B, spec, hcfg), recent=jnp.asarray(off)[:, None],
                                    recent_valid=jnp.ones((B, 1), bool))
        rows = []
        for _ in range(3):
            _, tokens, state, stats = run(params, CFG, hcfg, spec, tok, state, obs, kin, jnp.arange(B))
            np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
            rows.append(np.asarray(stats["skipped"]))
        skipped[bounds] = np.array(rows)
    np.testing.assert_array_equal(skipped[(None, None)], np.array([[0, 0, 1]] * B).T)
    np.testing.assert_array_equal(skipped[(2, 6)], np.array([[0, 1, 0]] * B).T)
    with pytest.raises(ValueError, match="both repeat_r_max and repeat_r_seq"):
        acceptance.SkipConfig(repeat_r_max=2)
    with pytest.raises(ValueError, match="need skip source 'recent'"):
        acceptance.SkipConfig(source="retrieval", repeat_r_max=2, repeat_r_seq=6)


def test_skip_max_metric_keeps_rows_in_fine_motion_verified(tiny_hybrid):
    """SkipConfig.max_metric: rows whose kinematic metric exceeds it verify every step (same
    tokens); rows below it skip as without the bound."""
    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    fast = jnp.arange(B) >= B // 2  # the second half of the rows moves: a high metric
    kin = hybrid.Kinematics(lin_vel=jnp.where(fast[:, None], 0.5, 0.0) * jnp.ones((B, 3)),
                            ang_vel=jnp.zeros((B, 3)), lin_acc=jnp.zeros((B, 3)), gripper_vel=jnp.zeros((B,)))
    skips = {}
    for bound in (float("inf"), 1e-3):
        hcfg = dataclasses.replace(STRICT, acceptance="seq_relaxed", n_candidates=0, recent_candidates=2,
                                   continuation="ar",
                                   skip=acceptance.SkipConfig(source="recent", n_confirm=1, k_skip=2, max_metric=bound))
        run = jax.jit(hybrid.step, static_argnums=(1, 2, 3, 4))
        state, skipped = hybrid.init_state(B, spec, hcfg), []
        for _ in range(5):
            _, tokens, state, stats = run(params, CFG, hcfg, spec, tok, state, obs, kin, jnp.arange(B))
            np.testing.assert_array_equal(np.asarray(tokens), ar_tokens)
            skipped.append(np.asarray(stats["skipped"]))
        metric = np.asarray(stats["metric"])
        assert np.all(metric[np.asarray(fast)] > 1e-3) and np.all(metric[~np.asarray(fast)] <= 1e-3)
        skips[bound] = np.array(skipped)
    slow = ~np.asarray(fast)
    assert skips[float("inf")].sum() > 0 and np.all(skips[float("inf")][:, slow] == skips[float("inf")][:, ~slow])
    np.testing.assert_array_equal(skips[1e-3][:, slow], skips[float("inf")][:, slow])
    assert not skips[1e-3][:, ~slow].any()


def test_compact_rows_runs_the_rows_that_need_the_target_in_the_smallest_bucket():
    assert hybrid.bucket_sizes(16, 4) == (4, 8, 12, 16) and hybrid.bucket_sizes(6, 4) == (2, 3, 5, 6)
    assert hybrid.bucket_sizes(1, 4) == (1,) and hybrid.bucket_sizes(5, 1) == (5,)
    rows = jnp.arange(16 * 7, dtype=jnp.int32).reshape(16, 7)

    def fn(r, sk):  # tokens: the rows doubled; stats: the batch it ran at, and what it saw skip
        return r * 2, {"batch": jnp.full(sk.shape, float(sk.shape[0])), "skipped": sk.astype(jnp.float32)}
    fallback = jnp.full((16, 7), -1, jnp.int32)
    run = jax.jit(lambda sk: hybrid.compact_rows(fn, rows, sk, fallback, 4, {"skipped": 1.0}))
    for need in (0, 3, 4, 5, 12, 16):
        skip = np.ones(16, bool)
        skip[np.random.default_rng(need).permutation(16)[:need]] = False
        tokens, stats = run(jnp.asarray(skip))
        ran = ~skip
        np.testing.assert_array_equal(np.asarray(tokens)[ran], np.asarray(rows)[ran] * 2)
        np.testing.assert_array_equal(np.asarray(tokens)[skip & (np.asarray(stats["batch"]) == 0)], -1)
        np.testing.assert_array_equal(np.asarray(stats["batch"])[ran], max(4, -(-need // 4) * 4))
        np.testing.assert_array_equal(np.asarray(stats["skipped"]), skip)


def test_row_buckets_give_the_same_actions_as_the_whole_batch(tiny_hybrid):
    """Half the rows skip (repeat their last action) and half verify: gathered into a smaller
    bucket, each row's tokens and stats are the same as decoded in the whole batch."""
    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    kin = hybrid.Kinematics(lin_vel=jnp.zeros((B, 3)), ang_vel=jnp.zeros((B, 3)), lin_acc=jnp.zeros((B, 3)),
                            gripper_vel=jnp.zeros((B,)))
    cand, _ = candidates(ar_tokens, np.random.default_rng(1))
    store = retrieval.Datastore(keys=jnp.zeros((B * 3, spec.dim)), sq_norms=jnp.zeros((B * 3,)),
                                tokens=jnp.asarray(cand).reshape(B * 3, 7), task=jnp.repeat(jnp.arange(B), 3))
    p = dict(params, store=store)
    base = dataclasses.replace(STRICT, acceptance="seq_relaxed", recent_candidates=1,
                               skip=acceptance.SkipConfig(source="recent", n_confirm=1, k_skip=1))
    run = jax.jit(hybrid.step, static_argnums=(1, 2, 3, 4))
    state = hybrid.init_state(B, spec, base)
    _, _, state, _ = run(p, CFG, base, spec, tok, state, obs, kin, jnp.arange(B))
    state = dataclasses.replace(state, repeats=jnp.arange(B) % 2)  # odd rows repeat, even rows verify
    for continuation in hybrid.CONTINUATION:  # drafter rounds, or single-token passes (the batched 7B setting)
        cfgs = {k: dataclasses.replace(base, row_buckets=k, continuation=continuation) for k in (1, 3)}
        out = {k: run(p, CFG, c, spec, tok, state, obs, kin, jnp.arange(B)) for k, c in cfgs.items()}
        np.testing.assert_array_equal(np.asarray(out[1][2].repeats), np.asarray(out[3][2].repeats))
        np.testing.assert_array_equal(np.asarray(out[1][3]["skipped"]), np.arange(B) % 2)
        np.testing.assert_array_equal(np.asarray(out[1][1]), np.asarray(out[3][1]))
        for key in hybrid.STAT_KEYS:
            np.testing.assert_allclose(np.asarray(out[1][3][key]), np.asarray(out[3][3][key]), err_msg=key)
    # budget=auto: the same, and every row (in the bucket or not) reports the option chosen
    auto = dataclasses.replace(base, budget=budget.BudgetConfig(mode="auto", trees=((2, 2, 4),)))
    n_opts = len(budget.options(auto.budget, auto.mode))
    pa = dict(p, costs=budget.Costs(fixed_ms=jnp.asarray([1.0] + [0.5] * (n_opts - 1)),
                                    round_ms=jnp.full((n_opts,), 0.1)))
    state_a = dataclasses.replace(hybrid.init_state(B, spec, auto), recent=state.recent,
                                  recent_valid=state.recent_valid, repeats=state.repeats)
    out = {k: run(pa, CFG, dataclasses.replace(auto, row_buckets=k), spec, tok, state_a, obs, kin, jnp.arange(B))
           for k in (1, 3)}
    np.testing.assert_array_equal(np.asarray(out[1][1]), np.asarray(out[3][1]))
    for key in out[1][3]:
        np.testing.assert_allclose(np.asarray(out[1][3][key]), np.asarray(out[3][3][key]), err_msg=key)
    assert sum(float(out[3][3][k][0]) for k in out[3][3] if k.startswith("budget_")) == 1.0
    with pytest.raises(ValueError, match="row_buckets must be >= 1"):
        dataclasses.replace(base, row_buckets=0)


def test_config_rejects_bad_settings():
    with pytest.raises(ValueError, match="valid: hybrid, retrieval, drafter"):
        hybrid.HybridConfig(mode="sometimes")
    with pytest.raises(ValueError, match="valid: strict, token_relaxed, seq_relaxed"):
        hybrid.HybridConfig(acceptance="loose")
    with pytest.raises(ValueError, match="switch skip off"):
        hybrid.HybridConfig(acceptance="strict")
    with pytest.raises(ValueError, match=r"n_candidates \+ recent_candidates must be <="):
        hybrid.HybridConfig(n_candidates=40).check_fits(CFG)
    with pytest.raises(ValueError, match="nothing to verify"):
        hybrid.HybridConfig(n_candidates=0, recent_candidates=0, skip=acceptance.SkipConfig(enabled=False))
    with pytest.raises(ValueError, match="n_candidates=0 .* switch skip off"):
        hybrid.HybridConfig(n_candidates=0, skip=acceptance.SkipConfig(source="retrieval"))
    with pytest.raises(ValueError, match="valid: drafter, ar"):
        hybrid.HybridConfig(continuation="eagle")
    with pytest.raises(ValueError, match="tau_on > tau_off"):
        kinematics.BoundaryConfig(tau_on=0.5, tau_off=0.8)


def test_heisd_method_loads_the_shipped_checkpoints_and_checks_settings():
    from envs import tasks
    from envs.env import TabletopEnv
    from heisd_jax.harness import methods

    env = TabletopEnv(tasks.get_tasks("goal"), methods.env_config("heisd"))
    policy = methods.make_policy("heisd", env, budget="fixed", top_k=4, depth=2, total_tokens=8)
    with np.load(methods.vla_policy.DEFAULT_DATASTORE / "datastore.npz") as shipped:
        assert policy.name == "heisd" and policy.params["store"].size == len(shipped["keys"]) > 10_000
    with pytest.raises(ValueError, match="pass batch_size"):  # budget=auto (the default) measures costs at it
        methods.make_policy("heisd", env)
    assert methods.check_settings("heisd", {"skip": "false", "k_skip": "2"}) == {"skip": False, "k_skip": 2}
    with pytest.raises(ValueError, match="unknown settings \\['tau'\\]; valid: dtype, matmul_precision, target_scale, unroll, attention, patchify, top_k"):
        methods.check_settings("heisd", {"tau": 1})
    with pytest.raises(ValueError, match="not a boolean"):
        methods.check_settings("heisd", {"skip": "maybe"})
    with pytest.raises(ValueError, match="switch skip off"):
        methods.check_settings("heisd", {"acceptance": "strict", "skip": True})
    assert methods.config("heisd", {"acceptance": "strict"}).decode.lossless
    # Verify-skip needs its source's candidates: off without them unless asked for.
    assert not methods.config("heisd", {"n_candidates": 0, "skip_source": "retrieval"}).decode.skip.enabled
    assert not methods.config("heisd", {"recent_candidates": 0}).decode.skip.enabled
    assert methods.config("heisd", {"n_candidates": 0}).decode.skip.enabled  # the recent actions remain
    assert not methods.config("heisd", {}).decode.lossless
    with pytest.raises(ValueError, match="unknown settings \\['top_k'\\]; valid: dtype"):
        methods.check_settings("ar", {"top_k": 4})


def test_heisd_decodes_as_plain_ar_where_no_draft_option_can_beat_it(monkeypatch):
    """budget=auto at a batch size above budget_max_batch (the default: 1), or with a cost
    table in which every draft option is dominated (as at batch 256 on an H100): the policy is
    AR's decode, so HeiSD cannot be slower than AR there; with a table where drafting can win,
    and with row buckets (where a skip saves time), it is the HeiSD step."""
    from envs import tasks
    from envs.env import TabletopEnv
    from heisd_jax import budget, cost_model
    from heisd_jax.harness import methods, vla_policy

    class Table:
        def __init__(self, fixed):
            self.fixed = fixed

        def costs(self):
            n = len(budget.options(methods.config("heisd").decode.budget, "hybrid"))
            return budget.Costs(fixed_ms=jnp.asarray([1.0] + [self.fixed] * (n - 1), jnp.float32),
                                round_ms=jnp.full((n,), 0.5, jnp.float32))

    env = TabletopEnv(tasks.get_tasks("goal"), methods.env_config("heisd"))
    ar_code = vla_policy.decoding_policy("ar", None, None, None, vla_policy.ar).act.__code__
    for fixed, given, as_ar in ((1.2, dict(budget_max_batch=256), True), (0.3, dict(budget_max_batch=256), False),
                                (1.2, dict(budget_max_batch=256, row_buckets=4), False), (0.3, {}, True)):
        tables = []
        monkeypatch.setattr(cost_model, "load_or_calibrate",
                            lambda *a, fixed=fixed, **k: tables.append(fixed) or Table(fixed))
        logs = []
        policy = methods.make_policy("heisd", env, batch_size=256, log=logs.append, **given)
        assert policy.name == "heisd"
        assert policy.meta.get("runs_as_ar", False) == as_ar, (fixed, given)
        assert ("decoding with plain AR" in " ".join(logs)) == as_ar
        assert (policy.act.__code__ is ar_code) == as_ar
        # Above budget_max_batch no cost table is loaded or measured at all.
        assert bool(tables) == ("budget_max_batch" in given)
    with pytest.raises(ValueError, match="budget_max_batch is only used with budget=auto"):
        methods.config("heisd", {"budget": "fixed", "budget_max_batch": 4})
    with pytest.raises(ValueError, match="max_batch must be >= 1"):
        budget.BudgetConfig(mode="auto", max_batch=0)


def test_missing_cost_tables_are_the_ones_make_policy_would_miss(monkeypatch, tmp_path):
    """`methods.missing_cost_tables` (configs and files only: what an entry point checks before
    it runs anything) names exactly the batch sizes at which `make_policy` without
    calibrate_costs raises MissingCostTable: budget=auto at batch 1 with an empty cache; none
    at a fixed budget, above budget_max_batch, for AR, or once the table is cached (here by
    make_policy's own calibrate path, only the measurement faked); the other dtype is another table."""
    from envs import tasks
    from envs.env import TabletopEnv
    from heisd_jax import budget, checkpoint, cost_model
    from heisd_jax.harness import methods, vla_policy

    env = TabletopEnv(tasks.get_tasks("goal"), methods.env_config("heisd"))

    def builds(batch, **given):
        try:
            methods.make_policy("heisd", env, batch_size=batch, cost_cache=tmp_path, log=lambda _: None, **given)
        except cost_model.MissingCostTable:
            return False
        return True

    def missing(sizes, name="heisd", **given):
        return methods.missing_cost_tables(name, sizes, cost_cache=tmp_path, **given)

    assert missing([1, 2]) == [1] and not builds(1) and builds(2)
    assert missing([1], budget="fixed") == [] and missing([1], name="ar") == []

    def fake(params, cfg, hcfg, batch, reps=5):
        names = [o.name for o in budget.options(hcfg.budget, hcfg.mode)]
        n = len(names)
        return cost_model.CostTable(key=cost_model.table_key(cfg, hcfg, batch), options=names, fixed_ms=[1.0] * n,
                                    round_ms=[0.5] * n, decode_ms=[1.0] * n, decode_rounds=[0.0] * n,
                                    pieces={"prefill_ms": {"0": 1.0}}, seconds=0.0)
    monkeypatch.setattr(cost_model, "calibrate", fake)
    methods.make_policy("heisd", env, batch_size=1, cost_cache=tmp_path, calibrate_costs=True, log=lambda _: None)
    assert missing([1]) == [] and builds(1)
    other = {"float32": "bfloat16", "bfloat16": "float32"}[checkpoint.read_config(vla_policy.DEFAULT_CHECKPOINT).dtype]
    assert missing([1], dtype=other) == [1] and not builds(1, dtype=other)


def test_measure_with_given_keys_equals_measure_with_its_own(tiny_hybrid):
    """`boundary.measure` (the calibration's and the datastore study's decode) with the keys
    passed in gives what it gives computing them from the action history, and queries with
    the keys given; recent candidates given are verified too; skipping the drafter-only
    decode changes no other column. The store holds
    each row's AR action under the row's own key (accepted whole) and an action a full half
    of the bins away under a far key."""
    from heisd_jax.harness.offline import boundary  # noqa: PLC0415

    params, obs, ar_tokens = tiny_hybrid
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    spec = retrieval.KeySpec(history=1)
    prev = np.random.default_rng(2).uniform(-1, 1, (B, 1, 7)).astype(np.float32)
    keys = np.asarray(retrieval.make_keys(spec, tok, prev, obs.proprio))
    far = keys + 100.0
    wrong = CFG.first_action_id + (ar_tokens - CFG.first_action_id + 128) % 256
    all_keys = jnp.asarray(np.concatenate([keys, far]))
    store = retrieval.Datastore(keys=all_keys, sq_norms=(all_keys * all_keys).sum(-1),
                                tokens=jnp.asarray(np.concatenate([ar_tokens, wrong])), task=jnp.tile(jnp.arange(B), 2))
    steps = {"image": np.asarray(obs.image), "instruction": np.asarray(obs.instruction),
             "proprio": np.asarray(obs.proprio), "prev": prev, "task": np.arange(B), "feat": np.zeros((B, 5))}
    hcfg = dataclasses.replace(STRICT, mode="hybrid", n_candidates=1)
    p = dict(params, store=store)
    own = boundary.measure(p, CFG, hcfg, spec, tok, steps, batch=4)
    given = boundary.measure(p, CFG, hcfg, spec, tok, {**steps, "key": keys}, batch=4, drafter_alone=False)
    to_far = boundary.measure(p, CFG, hcfg, spec, tok, {**steps, "key": far}, batch=4, drafter_alone=False)
    # the env's recent actions, verified beside the retrieved ones: the AR action among them is accepted whole
    recent = np.stack([wrong, ar_tokens], 1)
    with_recent = boundary.measure(p, CFG, hcfg, spec, tok, {**steps, "key": far, "recent": recent,
                                                             "recent_valid": np.ones((B, 2), bool)}, batch=4)
    assert (own["accepted"] == 7).all() and (to_far["accepted"] < 7).all() and (with_recent["accepted"] == 7).all()
    for k in ("metric", "tpa_retrieval", "accepted", "dist"):
        np.testing.assert_array_equal(own[k], given[k])
    assert np.isnan(given["tpa_drafter"]).all() and np.isfinite(own["tpa_drafter"]).all()
