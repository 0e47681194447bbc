"""MJX against MuJoCo C on the scene (float64, CPU), from an env reset state under controls that
clamp the servos' forces: the shipped physics agrees exactly until a servo clamps and then
drifts within the measured bound (MJX's implicitfast keeps a clamped servo's damping, MuJoCo C
drops it); the clamp-aware option agrees throughout (envs/physics.py)."""

import mujoco
import pytest

from envs import physics, physics_agreement as pa, scene, tasks
from envs.env import EnvConfig, TabletopEnv

CONTROL_STEPS = 4  # 40 physics steps: the initial targets held for 20, then two jumps
FAST_COMPILE = {"xla_backend_optimization_level": 0}  # compiles in 6 s instead of 15 on 2 cores


@pytest.fixture(scope="module")
def case():
    env = TabletopEnv(tasks.get_tasks("spatial", ["left_block_plate"]), EnvConfig(render=False))
    starts = pa.reset_starts(env, [0], [0])
    return starts, pa.jump_controls(starts, CONTROL_STEPS)


def test_shipped_physics_agrees_until_a_servo_clamps_then_within_the_measured_bound(case):
    a = pa.compare(physics.PhysicsConfig(), *case, one_step=False, compiler_options=FAST_COMPILE)
    assert a.clamped_fraction > 0.05  # the controls do clamp servos
    assert a.dq_before_first_clamp < 1e-12  # identical until the first clamped step ...
    # ... which alone moves a joint by ~1.6e-3 rad (a tiny difference here means MJX now
    # handles clamped forces as MuJoCo C does: make clamp_aware_implicit a no-op).
    assert 2e-4 < a.dq_first_clamp < 5e-3
    assert a.max_dq < 2e-2  # 5.1e-3 measured over these 40 steps


def test_clamp_aware_implicit_agrees_with_mujoco_c_through_clamped_steps(case):
    a = pa.compare(physics.PhysicsConfig(clamp_aware_implicit=True), *case, one_step=False, compiler_options=FAST_COMPILE)
    assert a.clamped_fraction > 0.05
    assert a.max_dq < 1e-12


def test_physics_config_compiles_the_settings_into_the_scene():
    cfg = physics.PhysicsConfig()  # the shipped default, one shared model
    assert physics.mj_model() is scene.build_model(cfg.integrator, cfg.force_limits, cfg.max_contacts, cfg.max_geom_pairs)
    m = physics.mj_model(physics.PhysicsConfig(integrator="rk4", force_limits=False))
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4 and not m.actuator_forcelimited.any()
    assert scene.build_model().actuator_forcelimited.all()
    with pytest.raises(ValueError, match="valid: implicitfast, euler, rk4"):
        physics.PhysicsConfig(integrator="implicit")
