"""End-effector kinematics read from MJX state: pose, velocities, acceleration, gripper.

The hybrid decoder's boundary detector (`heisd_jax.kinematics`) reads these every control
step. Velocities are exact (site Jacobian times joint velocities); the acceleration is the
finite difference of the linear velocity over one control step.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct
from mujoco import mjx

from envs import rotations
from envs.scene import SceneIds

PROPRIO_DIM = 8  # ee position (3), ee quaternion (4), gripper opening (1)


@struct.dataclass
class EEKinematics:
    pos: jnp.ndarray  # [3] tool centre point, world frame (m)
    quat: jnp.ndarray  # [4] tool frame orientation (w, x, y, z), w >= 0
    lin_vel: jnp.ndarray  # [3] m/s
    ang_vel: jnp.ndarray  # [3] rad/s, world frame
    lin_acc: jnp.ndarray  # [3] m/s^2, finite difference over one control step
    gripper: jnp.ndarray  # [] jaw opening (m), 0 closed .. 0.08 open
    gripper_vel: jnp.ndarray  # [] d(opening)/dt (m/s)


def ee_jacobian(m: mjx.Model, d: mjx.Data, ids: SceneIds) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Translational and rotational Jacobians of the tool centre point: [3, nv] each."""
    jacp, jacr = mjx.jac(m, d, d.site_xpos[ids.ee_site], jnp.asarray(m.site_bodyid)[ids.ee_site])
    return jacp.T, jacr.T


def ee_kinematics(m: mjx.Model, d: mjx.Data, ids: SceneIds, prev_lin_vel: jnp.ndarray, dt: float) -> EEKinematics:
    jacp, jacr = ee_jacobian(m, d, ids)
    v = jacp @ d.qvel
    return EEKinematics(
        pos=d.site_xpos[ids.ee_site],
        quat=rotations.mat_to_quat(d.site_xmat[ids.ee_site].reshape(3, 3)),
        lin_vel=v,
        ang_vel=jacr @ d.qvel,
        lin_acc=(v - prev_lin_vel) / dt,
        gripper=d.qpos[ids.finger_qpos].sum(),
        gripper_vel=d.qvel[ids.finger_dof].sum(),
    )


def proprio_vector(k: EEKinematics) -> jnp.ndarray:
    """[8] = ee position, ee quaternion, jaw opening: the policy's proprioceptive input."""
    return jnp.concatenate([k.pos, k.quat, k.gripper[None]])
