"""The simulator's settings (envs/physics.py). MJX's sums over a body's children in a fixed
order (`fixed_order_sums`): the same sums as `jax.ops.segment_sum`, no scatter-add with
repeated indices left in the env's traced step (on a GPU such a scatter-add runs with atomics,
in an order that changes from run to run), and on CPU the same physics up to float rounding.
The static solver loop: no while loop left, the same physics. The contact caps, the solver's
iteration caps, the substeps per control step and `--physics`' text form."""

import collections

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from envs import physics, tasks
from envs.env import EnvConfig, TabletopEnv


def test_fixed_order_segment_sum_equals_segment_sum():
    rng = np.random.default_rng(0)
    ids = np.array([0, 2, 2, 0, 2, 5, 4, 2])  # repeats, an empty segment (1, 3), an id out of range (5)
    data = jnp.asarray(rng.normal(size=(8, 3, 2)), jnp.float32)
    got = physics.fixed_order_segment_sum(data, ids, 5)
    want = jax.ops.segment_sum(data, ids, 5)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    assert got.shape == (5, 3, 2) and not np.any(got[1]) and not np.any(got[3])
    assert not np.any(physics.fixed_order_segment_sum(data, np.full(8, 9), 2))  # every id out of range


def test_summation_order_patches_only_static_ids_and_restores():
    original = jax.ops.segment_sum
    with physics.summation_order():
        with physics.summation_order():  # re-entrant
            assert jax.ops.segment_sum is not original
        assert jax.ops.segment_sum is not original
        traced = jnp.asarray([0, 1, 1])  # ids only known at run time: segment_sum itself
        np.testing.assert_allclose(jax.ops.segment_sum(jnp.ones(3), traced, 2), [1.0, 2.0])
    assert jax.ops.segment_sum is original
    with physics.summation_order(physics.PhysicsConfig(fixed_order_sums=False)):
        assert jax.ops.segment_sum is original


def _scatter_adds(fn, *args) -> collections.Counter:
    return _primitives("scatter-add", fn, *args)


def _primitives(name: str, fn, *args) -> collections.Counter:
    """Primitives `name` in fn's jaxpr (nested jaxprs included), by the innermost MJX source
    file that made them ('' if none)."""
    out = collections.Counter()

    def walk(jaxpr):
        for e in jaxpr.eqns:
            if e.primitive.name == name:
                tb = e.source_info.traceback
                files = [f.file_name for f in (tb.frames if tb else []) if "mjx/_src/" in f.file_name]
                out[files[0].split("mjx/_src/")[-1] if files else ""] += 1
            for sub in jax.extend.core.jaxprs_in_params(e.params):
                walk(sub)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return out


@pytest.fixture(scope="module")
def envs_and_state():
    task = tasks.get_tasks("spatial", ["left_block_plate"])
    fixed = TabletopEnv(task, EnvConfig(render=False))
    atomic = TabletopEnv(task, EnvConfig(render=False, physics=physics.PhysicsConfig(fixed_order_sums=False)))
    state = jax.jit(fixed.reset)(jax.random.PRNGKey(3), jnp.int32(0))
    return fixed, atomic, state


def test_no_body_tree_scatter_add_left_in_the_env_step(envs_and_state):
    fixed, atomic, state = envs_and_state
    action = jnp.full((7,), 0.3)
    tree_sums = lambda counts: sum(n for where, n in counts.items() if where == "scan.py")
    assert tree_sums(_scatter_adds(atomic.step, state, action)) > 0  # MJX's own: repeated indices
    left = _scatter_adds(fixed.step, state, action)
    assert tree_sums(left) == 0
    # What is left: math.axis_angle_to_quat's jnp.insert, one update per element. A new entry
    # here is a new MJX scatter-add: check whether its indices repeat.
    assert set(left) == {"math.py"}, left
    assert tree_sums(_scatter_adds(fixed.reset, jax.random.PRNGKey(0), jnp.int32(0))) == 0


def _roll(env, state, actions):
    return jax.jit(lambda s, a: jax.lax.scan(lambda s, u: (env.step(s, u), None), s, a)[0])(state, actions)


def test_fixed_order_physics_equals_mjx_own_up_to_rounding(envs_and_state):
    fixed, atomic, state = envs_and_state
    actions = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (3, 7)), jnp.float32)

    a, b = _roll(fixed, state, actions), _roll(atomic, state, actions)
    # 30 physics steps; the sums' order differs from XLA's scatter by rounding (1.5e-8 measured).
    np.testing.assert_allclose(a.data.qpos, b.data.qpos, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.data.qvel, b.data.qvel, rtol=0, atol=1e-4)
    assert not np.array_equal(a.data.qpos, np.asarray(state.data.qpos))  # the arm moved


def test_max_contacts_caps_the_solver_rows_and_off_leaves_the_scene_as_it_was():
    from mujoco import mjx  # noqa: PLC0415

    from envs import scene  # noqa: PLC0415

    assert scene.scene_mjcf(max_contacts=0) == scene.scene_mjcf()  # off: no MJX setting in the MJCF
    full = mjx.make_data(physics.mj_model(physics.PhysicsConfig(max_contacts=0, max_geom_pairs=0)))
    capped = mjx.make_data(physics.mj_model(physics.PhysicsConfig(max_contacts=32, max_geom_pairs=0)))
    assert capped._impl.contact.dist.shape == (32,) < full._impl.contact.dist.shape
    assert capped._impl.efc_J.shape[0] < full._impl.efc_J.shape[0] / 4  # condim 3: 4 pyramid rows a contact
    with pytest.raises(ValueError, match="max_contacts must be 0"):
        physics.PhysicsConfig(max_contacts=-1)


def test_max_geom_pairs_culls_the_narrow_phase_to_the_nearest_pairs():
    from mujoco import mjx  # noqa: PLC0415
    from mujoco.mjx._src import collision_driver  # noqa: PLC0415

    from envs import scene  # noqa: PLC0415

    assert scene.scene_mjcf(max_geom_pairs=0) == scene.scene_mjcf()
    full = mjx.make_data(physics.mj_model(physics.PhysicsConfig(max_contacts=0, max_geom_pairs=0)))
    culled = physics.mj_model(physics.PhysicsConfig(max_contacts=0, max_geom_pairs=8))
    # box-box (19 pairs) and box-mesh (22) keep 8 each, 4 contacts a pair; the plane pairs are never culled.
    assert collision_driver.make_condim(culled).shape == (184 - (19 - 8) * 4 - (22 - 8) * 4,)
    assert mjx.make_data(culled)._impl.contact.dist.shape[0] < full._impl.contact.dist.shape[0]
    with pytest.raises(ValueError, match="max_geom_pairs must be 0"):
        physics.PhysicsConfig(max_geom_pairs=-1)


def test_physics_settings_parse_from_text_and_back():
    cfg = physics.PhysicsConfig(max_contacts=0, fixed_order_sums=False, ls_iterations=6, integrator="rk4")
    assert physics.parse(physics.describe(cfg)) == cfg
    assert physics.parse("") == physics.PhysicsConfig() and physics.describe(physics.PhysicsConfig()) == ""
    assert physics.parse(" max_contacts = 16 , clamp_aware_implicit=true") == physics.PhysicsConfig(
        max_contacts=16, clamp_aware_implicit=True)
    for text, value in [("true", True), ("0", False), ("None", None)]:
        assert physics.parse(f"static_solver_loop={text}").static_solver_loop is value
    assert physics.parse(physics.describe(physics.PhysicsConfig(static_solver_loop=False))).static_solver_loop is False
    for bad, message in [("contacts=3", "a field among integrator"), ("max_contacts", "a field among"),
                         ("force_limits=yes", "takes true, 1, false, 0"),
                         ("static_solver_loop=auto", "takes true, 1, false, 0, none"),
                         ("integrator=leapfrog", "unknown integrator"),
                         ("solver=pgs", "valid: newton, cg"), ("tolerance=-1", "tolerance must be >= 0"),
                         ("substeps=0", "substeps must be at least 1")]:
        with pytest.raises(ValueError, match=message):
            physics.parse(bad)


def test_solver_settings_set_the_models_options_and_leave_the_scene_as_compiled():
    import mujoco  # noqa: PLC0415
    from envs import scene  # noqa: PLC0415

    cfg = physics.PhysicsConfig()
    assert physics.mj_model() is scene.build_model(cfg.integrator, cfg.force_limits, cfg.max_contacts, cfg.max_geom_pairs)
    m = physics.mj_model(physics.PhysicsConfig(solver_iterations=3, ls_iterations=7, solver="cg", tolerance=1e-5))
    assert (m.opt.iterations, m.opt.ls_iterations, m.opt.solver, m.opt.tolerance) == (
        3, 7, mujoco.mjtSolver.mjSOL_CG, 1e-5)
    o = scene.build_model().opt
    assert (o.iterations, o.ls_iterations, o.solver, o.tolerance) == (
        scene.SOLVER_ITERATIONS, scene.LS_ITERATIONS, mujoco.mjtSolver.mjSOL_NEWTON, scene.SOLVER_TOLERANCE)


def test_substeps_split_the_control_step_and_ramp_to_the_same_targets(envs_and_state):
    from envs import scene  # noqa: PLC0415

    env, _, state = envs_and_state
    coarse = TabletopEnv(env.tasks, EnvConfig(render=False, physics=physics.PhysicsConfig(substeps=4)))
    assert env.mj_model.opt.timestep == scene.TIMESTEP and coarse.mj_model.opt.timestep == scene.CONTROL_DT / 4
    action = jnp.asarray([0.5, -0.4, 0.3, 0.2, -0.1, 0.3, 1.0], jnp.float32)
    ramp, _ = coarse.step_stages[0](state, action)
    assert ramp.shape == (4, env.mj_model.nu)
    np.testing.assert_allclose(ramp[1, :7], (state.data.ctrl[:7] + ramp[-1, :7]) / 2, rtol=0, atol=1e-6)  # linear
    fine_next, coarse_next = jax.jit(env.step)(state, action), jax.jit(coarse.step)(state, action)
    for after in (fine_next, coarse_next):  # one control step of simulated time either way
        np.testing.assert_allclose(after.data.time - state.data.time, scene.CONTROL_DT, rtol=1e-5)
    np.testing.assert_array_equal(coarse_next.data.ctrl, fine_next.data.ctrl)  # the same IK target, reached by both ramps


def test_broad_phase_ranks_order_pairs_by_bounding_sphere_gap_per_env():
    rbound = np.array([0.1, 0.1, 0.5])
    pairs = np.array([[0, 1], [0, 2], [1, 2]])
    xpos = np.array([[[0, 0, 0], [1, 0, 0], [0, 2, 0]],  # gaps 0.8, 1.4, ~1.64
                     [[0, 0, 0], [3, 0, 0], [0, 0.5, 0]]])  # gaps 2.8, -0.1, ~2.44
    np.testing.assert_array_equal(physics.broad_phase_ranks(xpos, rbound, pairs), [[1, 2, 3], [3, 1, 2]])
    groups = physics.collision_groups(physics.mj_model())
    assert {k: len(v) for k, v in groups.items()} == {"plane-box": 2, "plane-mesh": 2, "box-box": 19, "box-mesh": 22,
                                                       "mesh-mesh": 1}


def test_static_solver_loop_leaves_no_while_loop_in_the_step_and_the_same_physics(envs_and_state):
    looped, _, state = envs_and_state
    static = TabletopEnv(looped.tasks, EnvConfig(render=False, physics=physics.PhysicsConfig(static_solver_loop=True)))
    action = jnp.full((7,), 0.3)
    assert _primitives("while", looped.step, state, action) == {"solver.py": 1}  # MJX's solver loop
    assert not _primitives("while", static.step, state, action)
    actions = jnp.asarray(np.random.default_rng(2).uniform(-1, 1, (3, 7)), jnp.float32)
    a, b = _roll(static, state, actions), _roll(looped, state, actions)
    np.testing.assert_allclose(a.data.qpos, b.data.qpos, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.data.qvel, b.data.qvel, rtol=0, atol=1e-4)


def test_physics_as_its_own_program_scans_the_solver_loop_on_a_gpu_unless_set(envs_and_state, monkeypatch):
    env, _, state = envs_and_state
    controls, physics_stage, _ = env.step_stages
    x = controls(state, jnp.full((7,), 0.3))
    assert _primitives("while", physics_stage, state, x) == {"solver.py": 1}  # a CPU: MJX's while loop
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert not _primitives("while", env.step_stages[1], state, x)
    assert _primitives("while", env.step, state, jnp.full((7,), 0.3)) == {"solver.py": 1}  # inside one program
    kept = TabletopEnv(env.tasks, EnvConfig(render=False, physics=physics.PhysicsConfig(static_solver_loop=False)))
    assert _primitives("while", kept.step_stages[1], state, x) == {"solver.py": 1}


def test_solver_iterations_count_the_solver_loop_capped_and_cut_short_by_the_tolerance(envs_and_state):
    env, _, state = envs_and_state
    d = _roll(env, state, jnp.asarray(np.random.default_rng(4).uniform(-1, 1, (3, 7)), jnp.float32)).data
    counts = {}
    for tol, cap in [(0.0, 4), (1e-1, 4), (1e-5, 1)]:  # one iteration: MJX runs it without a loop
        cfg = physics.PhysicsConfig(tolerance=tol, solver_iterations=cap)
        m = TabletopEnv(env.tasks, EnvConfig(render=False, physics=cfg)).model
        counts[tol] = int(jax.jit(lambda d: physics.solver_iterations(m, d, cfg))(d))
    assert 0 <= counts[1e-1] < counts[0.0] <= 4  # the tolerance is what stops the loop here
    assert counts[1e-5] == 1
