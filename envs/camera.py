"""RGB cameras rendered inside JAX by ray casting, one ray per pixel.

`cast` is MJX's ray caster (`mjx.ray`: the nearest hit over the visible geoms) with
`envs.raycast`'s tests: MJX's per-type tests written on components, and a convex mesh
intersected as the polyhedron its face planes bound instead of triangle by triangle. On a GPU
a view's rays are cast by one Pallas kernel (`cast_rays`), which gives the same hits.

Each pixel shows the colour of the first geom its ray hits, shaded by a Lambertian term
from normals estimated on the depth map and a mild distance falloff. Geom colours are an
input, so objects can be recoloured per episode without changing the (shared) model.

The policy's image holds one or more views of the same square size, tiled left to right
(`VIEWS`): the agent view (a fixed camera in front of the table) and, with `wrist=True`,
the wrist camera on the hand. A ViT over the tiled image patchifies each view separately
(the view size is a multiple of the patch size) and tells them apart by the patches'
learned position embeddings, as a per-view encoder with shared weights would.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from envs import raycast

BACKGROUND = np.array([0.55, 0.62, 0.70])
LIGHT_DIR = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])


VIEWS = ("agentview", "wrist")  # camera names (scene / robot MJCF), in tiling order


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    height: int = 64  # of each view
    width: int = 64  # of each view
    wrist: bool = False  # tile the wrist camera's view right of the agent view

    @property
    def views(self) -> tuple[str, ...]:
        return VIEWS if self.wrist else VIEWS[:1]

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """[H, W * n_views, 3]: the observation's image."""
        return (self.height, self.width * len(self.views), 3)


def pixel_rays(height: int, width: int, fovy_deg: float) -> np.ndarray:
    """[H, W, 3] unit ray directions in the camera frame (MuJoCo: looks along -z, y up)."""
    t = np.tan(np.deg2rad(fovy_deg) / 2)
    aspect = width / height
    ys = (1 - 2 * (np.arange(height) + 0.5) / height) * t
    xs = (2 * (np.arange(width) + 0.5) / width - 1) * t * aspect
    dirs = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], -np.ones((height, 1))), -1)
    return (dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)).astype(np.float32)


VISIBLE_GROUPS = (0, 1, 2)  # geom groups the cameras see (MuJoCo's default visible groups)


def visible_geoms(m: mjx.Model) -> np.ndarray:
    """bool [ngeom]: the geoms a camera shows (VISIBLE_GROUPS, not transparent)."""
    matid, alpha = np.asarray(m.geom_matid), np.asarray(m.geom_rgba)[:, 3]
    mat_alpha = np.asarray(m.mat_rgba)[matid, 3] if len(m.mat_rgba) else np.ones_like(alpha)
    return np.isin(m.geom_group, VISIBLE_GROUPS) & np.where(matid == -1, alpha != 0, mat_alpha != 0)


def cast(m: mjx.Model, d: mjx.Data, pnt: jnp.ndarray, vec: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(distance, geom id) of the first visible geom that the ray from `pnt` along `vec` hits,
    (-1, -1) if none: `mjx.ray(m, d, pnt, vec, geomgroup)` with `envs.raycast`'s tests."""
    return raycast.nearest_hit(m, d, raycast.ray_groups(m, visible_geoms(m)), pnt, vec)


def cast_rays(m: mjx.Model, d: mjx.Data, pnt: jnp.ndarray, vecs: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """`cast` of rays [R, 3] from one origin: on a GPU one Pallas kernel
    (`raycast.nearest_hits_kernel`, the same hits), elsewhere `cast` vmapped over the rays.
    With several devices the kernel runs only where a mesh is set for tracing (`jax.set_mesh`,
    as the evaluator does), whose devices then each cast their share of a batch of envs
    (`raycast.per_device_batching`); without one, GSPMD would gather every env's rays onto
    each device and run the whole kernel there, so `cast` runs instead."""
    groups = raycast.ray_groups(m, visible_geoms(m))
    if jax.default_backend() == "gpu" and (jax.device_count() == 1 or not jax.sharding.get_abstract_mesh().empty):
        return raycast.nearest_hits_kernel(m, d, groups, pnt, vecs)
    return jax.vmap(lambda v: raycast.nearest_hit(m, d, groups, pnt, v))(vecs)


def render_views(mj_model, m: mjx.Model, d: mjx.Data, geom_rgb: jnp.ndarray, cfg: CameraConfig) -> jnp.ndarray:
    """The observation image [H, W * n_views, 3] uint8: `cfg.views` tiled left to right.
    `mj_model` (the host model) supplies each camera's id and field of view."""
    return jnp.concatenate([
        render(m, d, mj_model.camera(v).id, geom_rgb, cfg.height, cfg.width, float(mj_model.camera(v).fovy[0]))
        for v in cfg.views], axis=1)


def view_hits(m: mjx.Model, d: mjx.Data, cam_id: int, height: int, width: int,
              fovy_deg: float) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """(distance [H, W], geom id [H, W], ray direction [H, W, 3] in the world) of each pixel of
    camera `cam_id`: the first visible geom its ray hits, (-1, -1) where none."""
    dirs = jnp.asarray(pixel_rays(height, width, fovy_deg)) @ d.cam_xmat[cam_id].reshape(3, 3).T
    dist, gid = cast_rays(m, d, d.cam_xpos[cam_id], dirs.reshape(-1, 3))
    return dist.reshape(height, width), gid.reshape(height, width), dirs


def view_geoms(mj_model, m: mjx.Model, d: mjx.Data, cfg: CameraConfig) -> jnp.ndarray:
    """[n_views, ngeom] bool: the geoms that some pixel of each of `cfg.views` shows."""
    rows = []
    for v in cfg.views:
        _, gid, _ = view_hits(m, d, mj_model.camera(v).id, cfg.height, cfg.width, float(mj_model.camera(v).fovy[0]))
        gid = jnp.where(gid >= 0, gid, mj_model.ngeom).ravel()  # a miss: past the end, dropped
        rows.append(jnp.zeros(mj_model.ngeom, bool).at[gid].set(True, mode="drop"))
    return jnp.stack(rows)


def render(m: mjx.Model, d: mjx.Data, cam_id: int, geom_rgb: jnp.ndarray, height: int, width: int,
           fovy_deg: float) -> jnp.ndarray:
    """RGB image [H, W, 3] uint8 from camera `cam_id`; `geom_rgb` [ngeom, 3] in [0, 1]."""
    origin = d.cam_xpos[cam_id]
    dist, gid, dirs = view_hits(m, d, cam_id, height, width, fovy_deg)
    hit = gid >= 0
    dist = jnp.where(hit, dist, 10.0)
    pts = origin + dirs * dist[..., None]
    # Normals from the depth map: cross product of neighbouring surface points.
    dx = jnp.concatenate([pts[:, 1:] - pts[:, :-1], pts[:, -1:] - pts[:, -2:-1]], 1)
    dy = jnp.concatenate([pts[1:] - pts[:-1], pts[-1:] - pts[-2:-1]], 0)
    n = jnp.cross(dx, dy)
    n = n / (jnp.linalg.norm(n, axis=-1, keepdims=True) + 1e-9)
    n = jnp.where(jnp.sum(n * dirs, -1, keepdims=True) > 0, -n, n)  # face the camera
    lambert = jnp.clip(jnp.sum(n * LIGHT_DIR, -1), 0.0, 1.0)
    shade = (0.45 + 0.55 * lambert) * jnp.clip(1.25 - 0.25 * dist, 0.6, 1.0)
    rgb = jnp.where(hit[..., None], geom_rgb[jnp.maximum(gid, 0)] * shade[..., None], BACKGROUND)
    return jnp.round(jnp.clip(rgb, 0.0, 1.0) * 255).astype(jnp.uint8)
