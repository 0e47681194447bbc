"""The action space (OpenVLA on LIBERO) and its map onto joint targets.

An action is 7 numbers in [-1, 1]: end-effector delta position (3, world frame), delta
rotation (3, world-frame axis-angle) and gripper (1: -1 open, +1 closed). Out-of-range
values are clipped. Deltas are scaled by `ControlConfig` and turned into arm joint targets by
damped-least-squares differential IK on the MJX model (Jacobian at the current joint state),
added to the previous joint targets.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from mujoco import mjx

from envs import proprio, robot
from envs.scene import SceneIds

ACTION_DIM = 7


@dataclasses.dataclass(frozen=True)
class ControlConfig:
    max_pos_step: float = 0.02  # m per control step at |action| = 1 (0.4 m/s at 20 Hz)
    max_rot_step: float = 0.12  # rad per control step at |action| = 1
    ik_damping: float = 0.05  # DLS damping lambda
    max_lead: float = 0.15  # rad: how far a joint target may run ahead of the joint


def action_to_ctrl(m: mjx.Model, d: mjx.Data, ids: SceneIds, action: jnp.ndarray, cfg: ControlConfig) -> jnp.ndarray:
    """[7] action -> [nu] actuator targets (7 arm joints, 2 fingers)."""
    a = jnp.clip(action, -1.0, 1.0)
    err = jnp.concatenate([a[:3] * cfg.max_pos_step, a[3:6] * cfg.max_rot_step])  # [6]
    jacp, jacr = proprio.ee_jacobian(m, d, ids)
    jac = jnp.concatenate([jacp, jacr])[:, ids.arm_dof]  # [6, 7]
    dq = jac.T @ jnp.linalg.solve(jac @ jac.T + cfg.ik_damping**2 * jnp.eye(6), err)
    # Integrate onto the previous joint target (the servos track a continuous reference), but
    # never let the target lead the measured joints by more than `max_lead` (a blocked arm
    # must not wind up).
    q = d.qpos[ids.arm_qpos]
    q_target = jnp.clip(d.ctrl[:7] + dq, q - cfg.max_lead, q + cfg.max_lead)
    q_target = jnp.clip(q_target, robot.ARM_LOWER, robot.ARM_UPPER)
    finger = robot.FINGER_OPEN * (1.0 - a[6]) / 2.0
    return jnp.concatenate([q_target, jnp.full((2,), finger)])
