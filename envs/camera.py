"""RGB cameras rendered inside JAX by ray casting, one ray per pixel.

`cast` is MJX's ray caster (`mjx.ray`: the nearest hit over the visible geoms) with one change:
a convex mesh is intersected as the polyhedron its face planes bound (a slab test per distinct
plane) instead of triangle by triangle. The hits are the same up to float rounding; the
scene's cylinders (octagonal prisms, 28 triangles but 10 planes) were half the camera's cost.

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
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import ray as mjx_ray

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
_PRIMITIVE_RAYS = {mujoco.mjtGeom.mjGEOM_PLANE: mjx_ray._ray_plane, mujoco.mjtGeom.mjGEOM_SPHERE: mjx_ray._ray_sphere,
                   mujoco.mjtGeom.mjGEOM_CAPSULE: mjx_ray._ray_capsule,
                   mujoco.mjtGeom.mjGEOM_ELLIPSOID: mjx_ray._ray_ellipsoid, mujoco.mjtGeom.mjGEOM_BOX: mjx_ray._ray_box}


def mesh_planes(vert: np.ndarray, face: np.ndarray, decimals: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """(normals [P, 3], offsets [P]) of a convex mesh's distinct face planes, outward: a point x
    is inside iff normals @ x <= offsets. Raises ValueError for a mesh that is not convex."""
    tri = vert[face].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = np.einsum("fi,fi->f", n, tri[:, 0])
    n = np.where((c < np.einsum("fi,i->f", n, vert.mean(0)))[:, None], -n, n)  # outward from the centroid
    c = np.einsum("fi,fi->f", n, tri[:, 0])
    _, keep = np.unique(np.round(np.concatenate([n, c[:, None]], 1), decimals), axis=0, return_index=True)
    n, c = n[np.sort(keep)], c[np.sort(keep)]
    scale = np.abs(vert).max()
    if np.any(vert @ n.T > c + 1e-6 * scale):
        raise ValueError("mesh_planes needs a convex mesh: a vertex lies outside one of its face planes")
    return n.astype(np.float32), c.astype(np.float32)


def _ray_convex(normals: jnp.ndarray, offsets: jnp.ndarray, pnt: jnp.ndarray, vec: jnp.ndarray) -> jnp.ndarray:
    """Distance along `vec` from `pnt` (the mesh's frame) to the polyhedron {x: normals @ x <=
    offsets}, inf on a miss: the last plane the ray enters before the first it leaves (the leaving
    plane when `pnt` is inside, as a triangle test hits the far face)."""
    a, b = normals @ vec, offsets - normals @ pnt  # b >= 0: pnt on the inner side of the plane
    t = mjx_ray.math.safe_div(b, a)
    t_in = jnp.max(jnp.where(a < 0, t, -jnp.inf))
    t_out = jnp.min(jnp.where(a > 0, t, jnp.inf))
    parallel_outside = jnp.any((a == 0) & (b < 0))
    dist = jnp.where(t_in >= 0, t_in, t_out)
    return jnp.where((t_in <= t_out) & (t_out >= 0) & ~parallel_outside, dist, jnp.inf)


def cast(m: mjx.Model, d: mjx.Data, pnt: jnp.ndarray, vec: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(distance, geom id) of the first visible geom (VISIBLE_GROUPS, not transparent) that
    the ray from `pnt` along `vec` hits, (-1, -1) if none: `mjx.ray(m, d, pnt, vec, geomgroup)`
    with convex meshes intersected by their face planes."""
    matid, alpha = np.asarray(m.geom_matid), np.asarray(m.geom_rgba)[:, 3]
    mat_alpha = np.asarray(m.mat_rgba)[matid, 3] if len(m.mat_rgba) else np.ones_like(alpha)
    visible = np.isin(m.geom_group, VISIBLE_GROUPS) & np.where(matid == -1, alpha != 0, mat_alpha != 0)
    local_pnt = jax.vmap(lambda x, y: x.T @ (pnt - y))(d.geom_xmat, d.geom_xpos)
    local_vec = jax.vmap(lambda x: x.T @ vec)(d.geom_xmat)
    dists, ids = [], []
    for geom_type, fn in _PRIMITIVE_RAYS.items():
        (idx,) = np.nonzero(visible & (m.geom_type == geom_type))
        if idx.size:
            dists.append(jax.vmap(fn)(m.geom_size[idx], local_pnt[idx], local_vec[idx]))
            ids.append(idx)
    faceadr = np.append(m.mesh_faceadr, len(m.mesh_face))  # as MJX's own ray caster reads them
    for g in np.nonzero(visible & (m.geom_type == mujoco.mjtGeom.mjGEOM_MESH))[0]:
        mesh = m.geom_dataid[g]
        vert = np.asarray(m.mesh_vert)[m.mesh_vertadr[mesh]:m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
        normals, offsets = mesh_planes(vert, np.asarray(m.mesh_face)[faceadr[mesh]:faceadr[mesh + 1]])
        dists.append(_ray_convex(jnp.asarray(normals), jnp.asarray(offsets), local_pnt[g], local_vec[g])[None])
        ids.append(np.array([g]))
    if not ids:
        return jnp.array(-1.0), jnp.array(-1)
    dists, ids = jnp.concatenate(dists), np.concatenate(ids)
    best = jnp.argmin(dists)
    miss = jnp.isinf(dists[best])
    return jnp.where(miss, -1.0, dists[best]), jnp.where(miss, -1, jnp.asarray(ids)[best])


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
    dist, gid = jax.vmap(lambda v: cast(m, d, d.cam_xpos[cam_id], v))(dirs.reshape(-1, 3))
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
