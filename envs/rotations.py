"""Small rotation helpers (jittable): rotation matrices, quaternions (w, x, y, z), rotation vectors."""

from __future__ import annotations

import jax.numpy as jnp


def mat_to_quat(r: jnp.ndarray) -> jnp.ndarray:
    """[..., 3, 3] rotation matrix -> [..., 4] unit quaternion (w, x, y, z) with w >= 0."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # Four candidate formulas; pick the numerically safest per element (largest diagonal term).
    t = jnp.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = jnp.argmax(t, -1)
    s = 0.5 / jnp.sqrt(jnp.maximum(jnp.take_along_axis(t, k[..., None], -1)[..., 0], 1e-12))
    r21, r12, r02, r20, r10, r01 = r[..., 2, 1], r[..., 1, 2], r[..., 0, 2], r[..., 2, 0], r[..., 1, 0], r[..., 0, 1]
    cands = jnp.stack(
        [
            jnp.stack([0.25 / s, (r21 - r12) * s, (r02 - r20) * s, (r10 - r01) * s], -1),
            jnp.stack([(r21 - r12) * s, 0.25 / s, (r01 + r10) * s, (r02 + r20) * s], -1),
            jnp.stack([(r02 - r20) * s, (r01 + r10) * s, 0.25 / s, (r12 + r21) * s], -1),
            jnp.stack([(r10 - r01) * s, (r02 + r20) * s, (r12 + r21) * s, 0.25 / s], -1),
        ],
        -2,
    )
    q = jnp.take_along_axis(cands, k[..., None, None], -2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


def quat_to_mat(q: jnp.ndarray) -> jnp.ndarray:
    """[..., 4] quaternion (w, x, y, z) -> [..., 3, 3] rotation matrix."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def yaw_quat(yaw: jnp.ndarray) -> jnp.ndarray:
    """Rotation about the world z axis as a quaternion."""
    return jnp.stack([jnp.cos(yaw / 2), jnp.zeros_like(yaw), jnp.zeros_like(yaw), jnp.sin(yaw / 2)], -1)


def quat_yaw(q: jnp.ndarray) -> jnp.ndarray:
    """Heading of a quaternion's x axis in the world xy plane."""
    r = quat_to_mat(q)
    return jnp.arctan2(r[..., 1, 0], r[..., 0, 0])


def mat_to_rotvec(r: jnp.ndarray) -> jnp.ndarray:
    """[..., 3, 3] -> [..., 3] axis * angle (log map), via the quaternion for stability near pi."""
    q = mat_to_quat(r)
    v = q[..., 1:]
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2 * jnp.arctan2(n, q[..., :1])
    return jnp.where(n > 1e-9, v / jnp.maximum(n, 1e-12) * angle, 2 * v)


def wrap_angle(a: jnp.ndarray, period: float = 2 * jnp.pi) -> jnp.ndarray:
    """Wraps an angle into [-period / 2, period / 2)."""
    return (a + period / 2) % period - period / 2
