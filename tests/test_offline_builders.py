"""The offline builders (heisd_jax.harness.offline): the boundary calibration's rule on a small
synthetic measurement, and the run-time retrieval module standing without them."""

import subprocess
import sys

import numpy as np
import pytest

from heisd_jax.harness.offline import boundary


def _measured(rng, n=40):
    """Metric 0..3.9 in steps of 0.1; retrieval needs fewer passes than the drafter below
    metric 2 and more from 2 on; the 25 nearest keys (dist 0..0.24) are accepted whole
    except the 3rd, the rest never."""
    metric = np.arange(n) / 10.0
    dist = np.arange(n) / 100.0
    accepted = np.where(np.arange(n) < 25, 7, 3)
    accepted[2] = 6
    perm = rng.permutation(n)  # the rule must not depend on the steps' order
    return {"metric": metric[perm], "tpa_retrieval": np.where(metric < 2.0, 2.0, 5.0)[perm],
            "tpa_drafter": np.full(n, 3.0), "accepted": accepted[perm], "dist": dist[perm]}


def test_boundary_rule_on_a_known_measurement():
    m = _measured(np.random.default_rng(0))
    rule = boundary.BoundaryRule(bins=4, hysteresis=0.5, skip_precision=0.9, min_skip_steps=20)
    edges, table = boundary.metric_table(m, rule.bins)
    np.testing.assert_allclose(edges, [0.0, 0.975, 1.95, 2.925, 3.9])
    assert [r["steps"] for r in table] == [10, 10, 10, 10]
    assert [r["tpa_retrieval"] for r in table] == [2.0, 2.0, 5.0, 5.0]
    # tau_on: the first bin where retrieval loses starts at 1.95 (its lower edge).
    result = boundary.calibrate(m, rule, min_dwell=3, about={"held_out_episodes": 2})
    assert result["tau_on"] == pytest.approx(1.95) and result["tau_off"] == pytest.approx(0.975)
    # skip_eps: the 25 nearest have 24/25 whole (>= 0.9); adding the 26th gives 24/26 = 0.92,
    # the 27th 24/27 = 0.89 < 0.9: the last distance that qualifies is the 26th's, 0.25.
    assert result["skip_eps"] == pytest.approx(0.25)
    assert list(result) == ["tau_on", "tau_off", "min_dwell", "skip_eps", "table", "steps", "held_out_episodes",
                            "overall"]
    assert result["min_dwell"] == 3 and result["steps"] == 40
    assert result["overall"]["retrieval_whole"] == pytest.approx(24 / 40)


def test_boundary_rule_edge_cases():
    m = _measured(np.random.default_rng(1))
    m["tpa_retrieval"] = np.full(40, 1.0)  # retrieval never loses: tau_on at the metric's top
    assert boundary.calibrate(m, boundary.BoundaryRule(bins=4), 3)["tau_on"] == pytest.approx(3.9)
    m["tpa_retrieval"] = np.full(40, 9.0)  # always loses: tau_on still keeps the lowest bin
    assert boundary.calibrate(m, boundary.BoundaryRule(bins=4), 3)["tau_on"] == pytest.approx(0.975)
    # Fewer whole acceptances than min_skip_steps: no skip distance.
    assert boundary.skip_eps(m["dist"], m["accepted"], 0.9, min_steps=30) == 0.0
    with pytest.raises(ValueError, match="hysteresis"):
        boundary.BoundaryRule(hysteresis=1.0)
    with pytest.raises(ValueError, match="bins"):
        boundary.BoundaryRule(bins=1)


def test_group_table_per_phase():
    """Per-group rows (the draft-source analysis by expert phase): the same statistics as the
    metric bins, each group's share of the steps, empty groups left out, in `names` order."""
    m = _measured(np.random.default_rng(1))
    groups = np.where(m["metric"] < 2.0, 2, 0)  # "c" below metric 2, "a" from 2 on, "b" never
    rows = boundary.group_table(m, groups, ("a", "b", "c"))
    assert [r["group"] for r in rows] == ["a", "c"]
    a, c = rows
    assert a["steps"] == c["steps"] == 20 and a["share"] == c["share"] == 0.5
    assert (a["tpa_retrieval"], c["tpa_retrieval"], a["tpa_drafter"]) == (5.0, 2.0, 3.0)
    assert c["retrieval_whole"] == 19 / 20 and a["retrieval_whole"] == 5 / 20


def test_closed_loop_steps_use_each_envs_own_executed_history():
    """The draft-source analysis turns a recorded [T, B] rollout into decode inputs: only the
    steps each env ran, its instruction and task, the actions it executed before each step as
    the retrieval history, and the previous step's velocity for the kinematic features."""
    t, b, h = 4, 3, 2
    rng = np.random.default_rng(0)
    traj = {"image": rng.integers(0, 255, (t, b, 2, 2, 3), dtype=np.uint8), "proprio": rng.normal(size=(t, b, 8)),
            "policy_action": np.arange(t * b * 7, dtype=np.float32).reshape(t, b, 7) / 100,
            "ee_vel": rng.normal(size=(t, b, 3)), "ee_ang_vel": rng.normal(size=(t, b, 3)),
            "ee_acc": rng.normal(size=(t, b, 3)), "gripper_vel": rng.normal(size=(t, b)),
            "teacher_stats": {"phase": np.tile(np.arange(t)[:, None], (1, b))}}
    instr = np.arange(b * 5).reshape(b, 5)
    steps, phase = boundary.closed_loop_steps(traj, np.array([3, 0, 4]), instr, np.array([7, 8, 9]), h)
    assert len(phase) == 7 and phase.tolist() == [0, 1, 2, 0, 1, 2, 3]
    assert steps["task"].tolist() == [7] * 3 + [9] * 4
    np.testing.assert_array_equal(steps["instruction"][3:], np.repeat(instr[2][None], 4, 0))
    np.testing.assert_array_equal(steps["image"][3:], traj["image"][:, 2])
    # env 2's step 2 saw its own executed actions of steps 0 and 1
    np.testing.assert_allclose(steps["prev"][5], traj["policy_action"][:2, 2])
    np.testing.assert_allclose(steps["prev"][3], 0.0)  # nothing before the first step
    from heisd_jax import kinematics  # noqa: PLC0415

    want = kinematics.features(traj["ee_vel"][1, 2], traj["ee_ang_vel"][1, 2], traj["ee_acc"][1, 2],
                               traj["gripper_vel"][1, 2], traj["ee_vel"][0, 2])
    np.testing.assert_allclose(steps["feat"][4], np.asarray(want), rtol=1e-5)
    with pytest.raises(ValueError, match="no running steps"):
        boundary.closed_loop_steps(traj, np.zeros(b, int), instr, np.array([7, 8, 9]), h)


def test_runtime_retrieval_imports_without_the_builders():
    code = ("import sys, heisd_jax.retrieval; "
            "bad = [m for m in sys.modules if m.startswith(('heisd_jax.harness.offline', 'envs', 'mujoco'))]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)
