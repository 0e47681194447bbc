"""HeiSD's rules on constructed cases: sequence-wise acceptance, verify-skip bounds, the
kinematic metric and the boundary's hysteresis and dwell."""

import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import acceptance as acc, kinematics as kin


def test_seq_relaxed_accepts_within_budget_and_stops_at_the_right_index():
    cfg = acc.SeqRelaxedConfig(r_max=15, r_seq=20)
    t = jnp.array([100, 100, 100, 100, 100, 100, 255])
    cases = [([100, 100, 100, 100, 100, 100, 255], 7),  # exact
             ([110, 95, 100, 100, 100, 100, 255], 7),  # 10 + 5 = 15 <= 20
             ([110, 95, 104, 102, 100, 100, 255], 3),  # cumulative 21 > 20 at index 3
             ([100, 116, 100, 100, 100, 100, 255], 1),  # one token 16 > r_max
             ([100, 100, 100, 100, 100, 100, 0], 6)]  # gripper disagrees: open vs closed
    for draft, n in cases:
        assert int(acc.seq_relaxed_length(jnp.array(draft), t, cfg)) == n, draft
    # one slightly-off dimension does not cut the action short, unlike token-wise r=3
    d = jnp.array([100, 108, 100, 100, 100, 100, 255])
    assert int(acc.seq_relaxed_length(d, t, cfg)) == 7
    with pytest.raises(ValueError, match="0 <= r_max < 256"):
        acc.SeqRelaxedConfig(r_max=300)
    with pytest.raises(ValueError, match="r_seq >= 0"):
        acc.SeqRelaxedConfig(r_seq=-1)


def test_verify_skip_is_bounded_and_only_in_retrieval_mode():
    cfg = acc.SkipConfig(eps=0.1, r_agree=2, n_agree=2, k_skip=2)
    b = 4
    cand = jnp.broadcast_to(jnp.arange(7), (b, 3, 7))
    dist = jnp.zeros((b, 3))
    valid = jnp.ones((b, 3), bool)
    in_ret = jnp.array([True, False, True, True])
    whole = jnp.array([True, True, False, True])
    skips = jnp.array([0, 0, 0, 2])
    np.testing.assert_array_equal(np.asarray(acc.may_skip(cfg, in_ret, dist, cand, valid, whole, skips)),
                                  [True, False, False, False])
    # simulate: consecutive skips never exceed k_skip
    s, n_skips = jnp.zeros(1, jnp.int32), []
    for _ in range(10):
        k = acc.may_skip(cfg, jnp.array([True]), dist[:1], cand[:1], valid[:1], jnp.array([True]), s)
        s = jnp.where(k, s + 1, 0)
        n_skips.append(int(s[0]))
    assert max(n_skips) == cfg.k_skip
    far = acc.may_skip(cfg, in_ret, dist + 1.0, cand, valid, whole, skips)
    disagree = acc.may_skip(cfg, in_ret, dist, cand.at[:, 1, 3].add(5), valid, whole, skips)
    off = acc.may_skip(acc.SkipConfig(enabled=False), in_ret, dist, cand, valid, whole, skips)
    assert not bool(far.any() | disagree.any() | off.any())


def test_repeat_skip_needs_confirmed_repeats_and_is_bounded():
    cfg = acc.SkipConfig(source="recent", n_confirm=2, k_skip=2)
    in_ret = jnp.array([True, False, True, True, True])
    last_valid = jnp.array([True, True, False, True, True])
    repeats = jnp.array([2, 2, 2, 1, 3])
    skips = jnp.array([0, 0, 0, 0, 2])
    np.testing.assert_array_equal(np.asarray(acc.may_repeat(cfg, in_ret, last_valid, repeats, skips)),
                                  [True, False, False, False, False])
    s, n_skips = jnp.zeros(1, jnp.int32), []
    for _ in range(10):
        k = acc.may_repeat(cfg, jnp.array([True]), jnp.array([True]), jnp.array([5]), s)
        s = jnp.where(k, s + 1, 0)
        n_skips.append(int(s[0]))
    assert max(n_skips) == cfg.k_skip and n_skips.count(0) == 3  # verify after every k_skip skips
    off = acc.may_repeat(acc.SkipConfig(source="recent", enabled=False), in_ret, last_valid, repeats, skips)
    assert not bool(off.any())
    with pytest.raises(ValueError, match="valid: retrieval, recent"):
        acc.SkipConfig(source="datastore")
    with pytest.raises(ValueError, match="n_confirm >= 1"):
        acc.SkipConfig(source="recent", n_confirm=0)


def test_fused_metric_matches_numpy_on_a_trajectory():
    rng = np.random.default_rng(0)
    v, w, a, g = (rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), rng.normal(size=20))
    prev = np.concatenate([np.zeros((1, 3)), v[:-1]])
    cfg = kin.MetricConfig(scales=(0.5, 1.0, 2.0, 0.1, 0.3), weights=(1.0, 0.5, 0.2, 1.0, 2.0))
    m = np.asarray(kin.fused_metric(kin.features(*map(jnp.asarray, (v, w, a, g, prev))), cfg))
    sp, psp = np.linalg.norm(v, axis=1), np.linalg.norm(prev, axis=1)
    cos = (v * prev).sum(1) / np.maximum(sp * psp, 1e-9)
    turning = np.where((sp > 1e-4) & (psp > 1e-4), 1 - np.clip(cos, -1, 1), 0.0)
    f = np.stack([sp, np.linalg.norm(w, axis=1), np.linalg.norm(a, axis=1), np.abs(g), turning], 1)
    np.testing.assert_allclose(m, (f * np.array(cfg.weights) / np.array(cfg.scales)).sum(1), rtol=1e-5)
    assert kin.scales_from_demos(f)[0] == pytest.approx(np.quantile(sp, 0.9))


def test_boundary_hysteresis_and_dwell_on_a_synthetic_profile():
    cfg = kin.BoundaryConfig(tau_on=1.5, tau_off=0.8, min_dwell=3)
    # fine work (high M), transport (low M) with a brief spike, then fine work again
    metric = [2.0] * 4 + [0.5] * 8 + [1.2, 1.6] + [0.5] * 4 + [2.0] * 6
    s, modes = kin.boundary_init(), []
    for m in metric:
        s = kin.boundary_step(s, jnp.asarray(m), cfg)
        modes.append(int(s.mode))
    modes = np.array(modes)
    assert np.all(modes[:4] == kin.DRAFTER) and modes[4] == kin.RETRIEVAL  # first low M after the dwell
    assert np.all(modes[4:12] == kin.RETRIEVAL) and modes[12] == kin.RETRIEVAL  # 1.2: between the thresholds
    assert modes[13] == kin.DRAFTER  # 1.6 > tau_on
    assert np.all(modes[13:17] == kin.DRAFTER)  # low M right after a switch waits out the dwell
    switches = np.flatnonzero(np.diff(modes) != 0)
    assert np.all(np.diff(switches) >= cfg.min_dwell)  # never flips faster than the dwell
    assert modes[-1] == kin.DRAFTER
    # 1.2 is between tau_off and tau_on: no switch on it alone
    with pytest.raises(ValueError, match="tau_on > tau_off"):
        kin.BoundaryConfig(tau_on=0.5, tau_off=0.8)
