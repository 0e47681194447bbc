"""The MJX environment: model, determinism, batching, IK, kinematics, bad input."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from scipy.spatial.transform import Rotation

from envs import proprio, scene, tasks
from envs.env import TabletopEnv

BATCH = 2  # envs per batch: every test here starts 2, so the session's compiled reset/step are reused


def test_mjcf_loads_in_mujoco_and_mjx():
    m = scene.build_model()
    assert m.nu == 9 and m.nq == 7 + 2 + 4 * 7
    mx = mjx.put_model(m)  # raises for unsupported geometry pairs (e.g. cylinder-box)
    assert mx.ngeom == m.ngeom
    d = mujoco.MjData(m)
    mujoco.mj_step(m, d)
    assert d.time == pytest.approx(m.opt.timestep) and np.all(np.isfinite(d.qpos))


def test_every_task_has_a_valid_instruction_and_goals():
    assert [len(s) for s in tasks.SUITES.values()] == [10, 10, 10, 10]
    names = [t.name for t in tasks.ALL_TASKS]
    assert len(set(names)) == len(names)
    assert all(1 <= len(t.goals) <= tasks.MAX_GOALS for t in tasks.ALL_TASKS)


def test_unknown_suite_or_task_lists_valid_names():
    with pytest.raises(ValueError, match="valid suites: spatial, object, goal, long"):
        tasks.get_tasks("kitchen")
    with pytest.raises(ValueError, match="valid tasks: .*red_block_plate"):
        tasks.get_tasks("goal", ["no_such_task"])


def test_reset_is_reproducible_and_places_objects_on_the_table(compiled):
    a = compiled.start([0, 25])
    b = compiled.start([0, 25])
    np.testing.assert_array_equal(a.data.qpos, b.data.qpos)
    pos = jax.vmap(compiled.env.object_pos)(a.data)
    np.testing.assert_allclose(pos[..., 2], np.broadcast_to(scene.OBJECT_HALF_HEIGHT, (BATCH, 4)), atol=1e-6)
    # Distinct initial states for distinct episodes of the same task.
    c = compiled.start([0, 0], episodes=(0, 1))
    assert not np.allclose(c.data.qpos[0], c.data.qpos[1])


def test_eval_and_train_initial_states_differ(compiled):
    env = compiled.env
    ev = env.initial_state_keys([0], [3], split="eval")
    tr = env.initial_state_keys([0], [3], split="train")
    assert not np.array_equal(ev, tr)


def test_cycling_eval_starts_go_over_tasks_then_evaluation_states(compiled):
    env = compiled.env
    n_tasks = len(env.tasks)
    tids, keys = env.cycling_eval_starts(2 * n_tasks + 1)
    assert tids.dtype == np.int32 and tids.tolist() == [*range(n_tasks)] * 2 + [0]
    np.testing.assert_array_equal(keys[n_tasks + 1], env.initial_state_keys([1], [1], split="eval")[0])
    np.testing.assert_array_equal(keys[-1], env.initial_state_keys([0], [2], split="eval")[0])


def test_step_is_deterministic(compiled):
    s = compiled.start([3, 17])
    a = jnp.tile(jnp.array([0.5, -0.3, 0.2, 0.0, 0.1, -0.2, -1.0]), (BATCH, 1))
    s1, s2 = compiled.step(s, a), compiled.step(s, a)
    for x, y in zip(jax.tree.leaves(s1), jax.tree.leaves(s2)):
        np.testing.assert_array_equal(x, y)


def test_reset_runs_only_the_pose_stage_of_the_forward_pass(compiled):
    """A reset computes poses (kinematics, com frames, cameras), not MJX's whole forward pass:
    the poses equal a full `mjx.forward`'s, and the state one step later is the one a fully
    forwarded reset state steps to (the step's own forward pass recomputes the rest)."""
    s = compiled.start([5, 33])
    fwd = jax.jit(jax.vmap(lambda d: mjx.forward(compiled.env.model, d)))(s.data)
    for name in ("xpos", "xmat", "site_xpos", "site_xmat", "geom_xpos", "geom_xmat", "cam_xpos", "cdof", "subtree_com"):
        np.testing.assert_allclose(getattr(s.data, name), getattr(fwd, name), rtol=0, atol=1e-6, err_msg=name)
    # The full pass's other outputs (velocity, actuation, dynamics, contacts and constraints)
    # on the same poses (another compiled program would round them differently).
    rest = ("qacc", "qfrc_bias", "qfrc_passive", "qfrc_actuator", "actuator_force", "actuator_length", "qfrc_smooth",
            "qacc_smooth", "qfrc_constraint", "cvel", "cdof_dot", "ten_length", "sensordata", "_impl")
    full = s.replace(data=s.data.replace(**{name: getattr(fwd, name) for name in rest}))
    assert not np.allclose(s.data.qfrc_bias, full.data.qfrc_bias)  # the reset really skipped the dynamics
    a = jnp.array([[0.8, 0.0, -0.5, 0.0, 0.0, 0.3, -1.0], [-0.4, 0.6, 0.0, 0.2, 0.0, 0.0, 1.0]])
    for x, y in zip(jax.tree.leaves(compiled.step(s, a)), jax.tree.leaves(compiled.step(full, a))):
        np.testing.assert_array_equal(x, y)


def test_vmapped_batch_equals_envs_stepped_one_at_a_time(compiled):
    s = compiled.start([5, 33])
    a = jnp.array([[0.8, 0.0, -0.5, 0.0, 0.0, 0.3, -1.0], [-0.4, 0.6, 0.0, 0.2, 0.0, 0.0, 1.0]])
    batched = compiled.step(s, a)
    # The same compiled batch function, fed each env twice (so no other env shares the batch).
    for i in range(BATCH):
        single = jax.tree.map(lambda x: jnp.stack([x[i], x[i]]), s)
        out = compiled.step(single, jnp.stack([a[i], a[i]]))
        np.testing.assert_allclose(out.data.qpos[0], batched.data.qpos[i], rtol=0, atol=1e-6)
        np.testing.assert_allclose(out.kin.lin_vel[0], batched.kin.lin_vel[i], rtol=0, atol=1e-5)


def test_ik_follows_commanded_deltas(compiled):
    s = compiled.start([0, 0])
    cfg = compiled.env.config.control
    commands = jnp.array([[1.0, 0, 0, 0, 0, 0, -1], [0, 0, -1.0, 0, 0, 0, -1]])
    p0 = np.asarray(s.kin.pos)
    n = 8
    for _ in range(n):
        s = compiled.step(s, commands)
    moved = np.asarray(s.kin.pos) - p0
    want = np.asarray(commands[:, :3]) * cfg.max_pos_step * n
    for i in range(BATCH):
        axis = int(np.argmax(np.abs(want[i])))
        ratio = moved[i, axis] / want[i, axis]
        assert 0.75 < ratio < 1.1, (i, moved[i], want[i])
        off_axis = np.delete(moved[i], axis)
        assert np.all(np.abs(off_axis) < 0.15 * abs(want[i, axis])), moved[i]


def test_ik_rotates_about_the_commanded_axis(compiled):
    s = compiled.start([0, 0])
    cmd = jnp.tile(jnp.array([0, 0, 0, 0, 0, 1.0, -1]), (BATCH, 1))
    s = compiled.step(s, cmd)
    s = compiled.step(s, cmd)
    w = np.asarray(s.kin.ang_vel)
    assert np.all(w[:, 2] > 1.5) and np.all(np.abs(w[:, :2]) < 0.3)


@pytest.mark.slow  # one MJX physics step and forward kinematics run eagerly: ~70 s on 2 cores
def test_kinematic_velocities_agree_with_finite_differences(compiled):
    env = compiled.env
    s = compiled.start([0, 0])
    s = compiled.step(s, jnp.tile(jnp.array([0.7, -0.5, 0.4, 0.3, 0.0, 0.5, -1.0]), (BATCH, 1)))
    d = jax.tree.map(lambda x: x[0], s.data)
    k = jax.tree.map(lambda x: x[0], s.kin)
    # One physics step forward: finite differences of the TCP position, orientation and jaw
    # opening agree with the velocities reported after the step (MuJoCo's semi-implicit Euler
    # moves positions with the updated velocity).
    d2 = mjx.com_pos(env.model, mjx.kinematics(env.model, mjx.step(env.model, d)))
    k2 = proprio.ee_kinematics(env.model, d2, env.ids, k.lin_vel, scene.TIMESTEP)
    dt = scene.TIMESTEP
    v_fd = (d2.site_xpos[env.ids.ee_site] - d.site_xpos[env.ids.ee_site]) / dt
    r1 = np.asarray(d.site_xmat[env.ids.ee_site]).reshape(3, 3)
    r2 = np.asarray(d2.site_xmat[env.ids.ee_site]).reshape(3, 3)
    w_fd = Rotation.from_matrix(r2 @ r1.T).as_rotvec() / dt
    v_new, w_new = k2.lin_vel, k2.ang_vel
    assert np.linalg.norm(v_new) > 0.05 and np.linalg.norm(w_new) > 0.2  # really moving
    np.testing.assert_allclose(v_fd, v_new, atol=0.02 * np.linalg.norm(v_new) + 1e-3)
    np.testing.assert_allclose(w_fd, w_new, atol=0.02 * np.linalg.norm(w_new) + 1e-2)
    g_fd = (d2.qpos[env.ids.finger_qpos].sum() - d.qpos[env.ids.finger_qpos].sum()) / dt
    np.testing.assert_allclose(g_fd, k2.gripper_vel, atol=1e-3)
    # Acceleration is the finite difference of the velocity over one control step.
    s2 = compiled.step(s, jnp.zeros((BATCH, 7)))
    np.testing.assert_allclose(s2.kin.lin_acc, (s2.kin.lin_vel - s.kin.lin_vel) / scene.CONTROL_DT, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(s2.obs.proprio[:, :3], s2.kin.pos)


def test_out_of_range_actions_are_clipped(compiled):
    s = compiled.start([1, 2])
    big = jnp.array([[5.0, -3.0, 2.0, 0.0, 9.0, -7.0, 4.0]] * BATCH)
    np.testing.assert_array_equal(compiled.step(s, big).data.qpos, compiled.step(s, jnp.clip(big, -1, 1)).data.qpos)


def test_non_finite_action_fails_only_that_env(compiled):
    s = compiled.start([4, 4])
    a = jnp.array([[jnp.nan, 0, 0, 0, 0, 0, 0], [0.3, 0, 0, 0, 0, 0, -1.0]])
    out = compiled.step(s, a)
    assert bool(out.invalid_action[0]) and bool(out.done[0]) and not bool(out.success[0])
    assert not bool(out.invalid_action[1]) and not bool(out.done[1])
    ref = compiled.step(s, a.at[0].set(0.0))
    np.testing.assert_array_equal(out.data.qpos[1], ref.data.qpos[1])
    # A finished env is frozen.
    again = compiled.step(out, jnp.ones((BATCH, 7)) * 0.5)
    np.testing.assert_array_equal(again.data.qpos[0], out.data.qpos[0])
    assert int(again.step[0]) == int(out.step[0])


def test_simulator_blowup_ends_only_that_episode(compiled):
    s = compiled.start([6, 6])
    qvel = s.data.qvel.at[0, compiled.env.ids.object_dof[0]].set(jnp.inf)
    s = s.replace(data=s.data.replace(qvel=qvel))
    out = compiled.step(s, jnp.zeros((BATCH, 7)))
    assert bool(out.unstable[0]) and bool(out.done[0])
    assert np.all(np.isfinite(out.data.qpos[0]))  # the last finite state is kept
    assert not bool(out.unstable[1]) and not bool(out.done[1])
    assert np.all(np.isfinite(out.data.qpos[1]))


def test_relational_goals_resolve_unambiguously(compiled):
    env = compiled.env
    left = [t.name for t in env.tasks].index("left_block_plate")
    right = [t.name for t in env.tasks].index("right_block_plate")
    s = compiled.start([left, right], episodes=(7, 7))  # same layout key? different tasks -> different keys
    pos = jax.vmap(env.object_pos)(s.data)
    for i, sign in ((0, 1), (1, -1)):
        target = int(s.info.goal_obj[i, 0])
        other = 1 - target  # the other block
        assert target in (0, 1)
        assert sign * (pos[i, other, 1] - pos[i, target, 1]) >= tasks.SELECTOR_MARGIN - 1e-6
