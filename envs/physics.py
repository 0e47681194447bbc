"""The simulator's settings and its physics step: the integrator, the servos' force limits, and
how MJX's `implicitfast` treats a servo whose force is clamped.

MuJoCo C (since 3.5.0, Feb 2026: `mjd_actuator_vel` in engine_derivative.c, "skip if force is
clamped by forcerange") leaves a servo's velocity derivative (-kv) out of the implicit
integrator's matrix M - h dF/dv while the servo's force sits at its `forcerange`: the clamped
force does not depend on the velocity. MJX's JAX implementation (mujoco-mjx 3.17.0,
`mujoco/mjx/_src/derivative.py: deriv_smooth_vel`) keeps it, so under `implicitfast` it damps a
saturated joint that MuJoCo C does not, and the two drift apart from the first clamped step on
(`envs.physics_agreement` measures it). `clamp_aware_implicit=True` gives MJX MuJoCo C's rule;
the default keeps MJX's, the physics the shipped policies were trained and evaluated under.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import mujoco
from mujoco import mjx
from mujoco.mjx._src import forward as mjx_forward  # MJX's own implicitfast integrator step

from envs import scene

INTEGRATORS = ("implicitfast", "euler", "rk4")


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    integrator: str = "implicitfast"  # one of INTEGRATORS
    force_limits: bool = True  # the servos' forcerange (arm 87 / 12 Nm, fingers 20 N); False: unlimited
    # implicitfast only: leave a clamped servo's velocity derivative out of the implicit step,
    # as MuJoCo C does (False: MJX's own rule, which keeps it).
    clamp_aware_implicit: bool = False

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {self.integrator!r}; valid: {', '.join(INTEGRATORS)}")


def mj_model(cfg: PhysicsConfig = PhysicsConfig()) -> mujoco.MjModel:
    """The scene compiled with these settings (cached per setting)."""
    return scene.build_model(cfg.integrator, cfg.force_limits)


def clamped(m: mjx.Model, force: jnp.ndarray) -> jnp.ndarray:
    """[nu] bool: actuators whose force sits at a bound of their forcerange (MuJoCo C's test)."""
    lo, hi = m.actuator_forcerange[:, 0], m.actuator_forcerange[:, 1]
    return jnp.asarray(m.actuator_forcelimited, bool) & ((force <= lo) | (force >= hi))


def step(m: mjx.Model, d: mjx.Data, cfg: PhysicsConfig = PhysicsConfig()) -> mjx.Data:
    """One physics step: `mjx.step`, or with `cfg.clamp_aware_implicit` under implicitfast,
    MJX's forward dynamics and implicit step with the clamped servos' velocity terms zeroed."""
    if not (cfg.clamp_aware_implicit and cfg.integrator == "implicitfast"):
        return mjx.step(m, d)
    d = mjx.forward(m, d)
    # MJX's implicit step reads each servo's velocity derivative from biasprm[:, 2] (kv of a
    # position servo) and gainprm[:, 2]; zero them for the servos clamped in this forward pass.
    free = ~clamped(m, d.actuator_force)
    m_step = m.replace(actuator_biasprm=m.actuator_biasprm.at[:, 2].multiply(free),
                       actuator_gainprm=m.actuator_gainprm.at[:, 2].multiply(free))
    return mjx_forward.implicit(m_step, d)
