"""Ray-geom intersection tests and the casters that find a ray's nearest hit.

Each test is MJX's (`mujoco.mjx._src.ray`) for that geom type, with the same arithmetic written
on components: a product of two 3-vectors is three products and two sums, and a box's or a
convex mesh's faces are a chain of elementwise minima and maxima. So the same function runs
on one ray (`nearest_hit`, vmapped over a camera's rays) and on a block of rays inside a
Pallas kernel (`nearest_hits_kernel`, the GPU's caster). Batched over envs, rays and geoms,
MJX's dots lower to matrix products and reductions whose [envs, rays, geoms] outputs XLA
writes to memory and reads back (gigabytes per view at 4,096 envs); the kernel keeps each
ray's running nearest hit in registers instead.

All tests take a geom's `size`, and the ray's origin `pnt` and direction `vec` in the geom's
frame, each as its components (a [3] array, or three arrays or scalars), and return the
distance along `vec` to the first hit, inf on a miss. A convex mesh is intersected as the
polyhedron its face planes bound (`mesh_planes`, `ray_convex`) instead of triangle by
triangle: the hits are the same up to float rounding, at a fraction of the cost.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax import lax
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pltriton
from mujoco.mjx._src.math import safe_div
from mujoco.mjx._src.ray import _ray_quad


def dot3(a, b):
    """a . b of two 3-vectors given as their components (a[0], a[1], a[2]: arrays, scalars or
    a [3] array), as products and sums."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _nearest_root(a, b, c):
    """The smaller non-negative root of a x^2 + 2 b x + c = 0, inf if none."""
    x0, x1 = _ray_quad(a, b, c)
    return jnp.where(jnp.isinf(x0), x1, x0)


def ray_plane(size, pnt, vec):
    """A plane z = 0 hit from its front (+z), within its rendered half sizes where positive."""
    x = -safe_div(pnt[2], vec[2])
    valid = (vec[2] <= -mujoco.mjMINVAL) & (x >= 0)
    for i in (0, 1):
        valid &= (size[i] <= 0) | (jnp.abs(pnt[i] + x * vec[i]) <= size[i])
    return jnp.where(valid, x, jnp.inf)


def ray_sphere(size, pnt, vec):
    return _nearest_root(dot3(vec, vec), dot3(vec, pnt), dot3(pnt, pnt) - size[0] * size[0])


def ray_ellipsoid(size, pnt, vec):
    s = [safe_div(1, size[i] * size[i]) for i in range(3)]
    svec, spnt = [s[i] * vec[i] for i in range(3)], [s[i] * pnt[i] for i in range(3)]
    return _nearest_root(dot3(svec, vec), dot3(svec, pnt), dot3(spnt, pnt) - 1)


def ray_capsule(size, pnt, vec):
    """A capsule along z: radius size[0], half length size[1]."""
    r, h = size[0], size[1]
    x = _nearest_root(vec[0] * vec[0] + vec[1] * vec[1], vec[0] * pnt[0] + vec[1] * pnt[1],
                      pnt[0] * pnt[0] + pnt[1] * pnt[1] - r * r)  # the round side...
    x = jnp.where(jnp.abs(pnt[2] + x * vec[2]) <= h, x, jnp.inf)  # ...between the flat ends
    vv = dot3(vec, vec)
    for side in (1.0, -1.0):  # the top sphere's upper half, the bottom one's lower half
        dz = pnt[2] - side * h
        for root in _ray_quad(vv, vec[0] * pnt[0] + vec[1] * pnt[1] + vec[2] * dz,
                              pnt[0] * pnt[0] + pnt[1] * pnt[1] + dz * dz - r * r):
            z = pnt[2] + root * vec[2]
            x = jnp.where(((z >= h) if side > 0 else (z <= -h)) & (root < x), root, x)
    return x


def ray_box(size, pnt, vec):
    """A box of half sizes size[:3]: the nearest of its six faces' hits."""
    best = jnp.inf
    for i, (j, k) in enumerate(((1, 2), (0, 2), (0, 1))):
        for x in (safe_div(size[i] - pnt[i], vec[i]), -safe_div(size[i] + pnt[i], vec[i])):
            valid = (jnp.abs(pnt[j] + x * vec[j]) <= size[j]) & (jnp.abs(pnt[k] + x * vec[k]) <= size[k]) & (x >= 0)
            best = jnp.minimum(best, jnp.where(valid, x, jnp.inf))
    return best


PRIMITIVE_RAYS = {mujoco.mjtGeom.mjGEOM_PLANE: ray_plane, mujoco.mjtGeom.mjGEOM_SPHERE: ray_sphere,
                  mujoco.mjtGeom.mjGEOM_CAPSULE: ray_capsule, mujoco.mjtGeom.mjGEOM_ELLIPSOID: ray_ellipsoid,
                  mujoco.mjtGeom.mjGEOM_BOX: ray_box}


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


def ray_convex(normals: np.ndarray, offsets: np.ndarray, pnt, vec):
    """Distance along `vec` from `pnt` (the mesh's frame) to the polyhedron {x: normals @ x <=
    offsets} (host arrays, one plane per row), inf on a miss: the last plane the ray enters
    before the first it leaves (the leaving plane when `pnt` is inside, as a triangle test hits
    the far face)."""
    t_in, t_out, parallel_outside = -jnp.inf, jnp.inf, False
    for n, c in zip(np.asarray(normals, np.float32), np.asarray(offsets, np.float32)):
        a, b = dot3(n, vec), c - dot3(n, pnt)  # b >= 0: pnt on the inner side of the plane
        t = safe_div(b, a)
        t_in = jnp.maximum(t_in, jnp.where(a < 0, t, -jnp.inf))
        t_out = jnp.minimum(t_out, jnp.where(a > 0, t, jnp.inf))
        parallel_outside |= (a == 0) & (b < 0)
    dist = jnp.where(t_in >= 0, t_in, t_out)
    return jnp.where((t_in <= t_out) & (t_out >= 0) & ~parallel_outside, dist, jnp.inf)


def first_min(dists: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(min, the first index where it is reached) over the last axis, as one reduction (no
    second pass over the distances to read the minimum at the index). The first index, as
    `jnp.argmin`: the order of the geoms decides a tie."""
    index = lax.broadcasted_iota(jnp.int32, dists.shape, dists.ndim - 1)

    def keep_first(x, y):
        (dx, ix), (dy, iy) = x, y
        take_y = (dy < dx) | ((dy == dx) & (iy < ix))
        return jnp.where(take_y, dy, dx), jnp.where(take_y, iy, ix)

    init = (np.array(np.inf, dists.dtype), np.array(np.iinfo(np.int32).max, np.int32))
    return lax.reduce((dists, index), init, keep_first, (dists.ndim - 1,))


@dataclasses.dataclass(frozen=True)
class RayGroup:
    """Geoms intersected by one test: a primitive type's geoms, or one convex mesh."""
    ids: np.ndarray  # geom ids, ascending
    test: Callable  # (size, pnt, vec) -> distance, all in the geom's frame


def ray_groups(m, geoms: np.ndarray) -> tuple[RayGroup, ...]:
    """The geoms where `geoms` (bool [ngeom]) is set, grouped in `mjx.ray`'s order: the
    primitive types in PRIMITIVE_RAYS's order, then each mesh (by its face planes)."""
    groups = []
    for geom_type, fn in PRIMITIVE_RAYS.items():
        (idx,) = np.nonzero(geoms & (np.asarray(m.geom_type) == geom_type))
        if idx.size:
            groups.append(RayGroup(idx, fn))
    faceadr = np.append(m.mesh_faceadr, len(m.mesh_face))  # as MJX's own ray caster reads them
    for g in np.nonzero(geoms & (np.asarray(m.geom_type) == mujoco.mjtGeom.mjGEOM_MESH))[0]:
        mesh = m.geom_dataid[g]
        vert = np.asarray(m.mesh_vert)[m.mesh_vertadr[mesh]:m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
        planes = mesh_planes(vert, np.asarray(m.mesh_face)[faceadr[mesh]:faceadr[mesh + 1]])
        groups.append(RayGroup(np.array([g]), functools.partial(_mesh_test, *planes)))
    return tuple(groups)


def _mesh_test(normals, offsets, size, pnt, vec):
    del size  # a mesh's extent is its planes
    return ray_convex(normals, offsets, pnt, vec)


def to_geom_frames(xmat: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """xmat^T v (xmat [..., 3, 3], v [..., 3]): v in each geom's frame, as products and sums."""
    return xmat[..., 0, :] * v[..., 0, None] + xmat[..., 1, :] * v[..., 1, None] + xmat[..., 2, :] * v[..., 2, None]


def nearest_hit(m, d, groups: tuple[RayGroup, ...], pnt: jnp.ndarray, vec: jnp.ndarray):
    """(distance, geom id) of the nearest of `groups`' geoms that the ray from `pnt` along `vec`
    (world frame) hits, (-1, -1) if none; a tie goes to the earlier group, then the lower id.
    One ray: vmap it over a camera's rays. Each group is one reduction (`first_min`)."""
    local_pnt = to_geom_frames(d.geom_xmat, pnt - d.geom_xpos)  # [ngeom, 3]
    best_dist, best_id = jnp.inf, jnp.int32(-1)
    for group in groups:
        local_vec = to_geom_frames(d.geom_xmat[group.ids], vec)
        dist, i = first_min(jax.vmap(group.test)(m.geom_size[group.ids], local_pnt[group.ids], local_vec))
        nearer = dist < best_dist  # strictly: an earlier group keeps a tie
        best_dist = jnp.where(nearer, dist, best_dist)
        best_id = jnp.where(nearer, jnp.asarray(group.ids, jnp.int32)[i], best_id)
    miss = jnp.isinf(best_dist)
    return jnp.where(miss, -1.0, best_dist), jnp.where(miss, -1, best_id)


# A geom's row in the kernel's table: xmat (9, row-major), the ray origin in the geom's frame (3),
# size (3), the geom's centre relative to the ray origin in the world frame (3).
_GEOM_ROW = 18
# A geom's bounding sphere (radius geom_rbound) as the kernel's cull test widens it, so that
# float rounding never culls a geom that a ray might hit: radius * (1 + _CULL_SLACK) + _CULL_PAD.
_CULL_SLACK, _CULL_PAD = 1e-3, 1e-5


def _misses_sphere(centre, radius: float, vec):
    """Whether the ray from the origin along `vec` (components) surely misses the sphere of
    `radius` (a host float) around `centre` (components, relative to the ray's origin), with
    the sphere widened for rounding: the line passes outside it, or the centre lies behind the
    origin (the distance to the sphere only grows along the ray) and the origin outside it."""
    r2 = (radius * (1 + _CULL_SLACK) + _CULL_PAD) ** 2
    cc, t, vv = dot3(centre, centre), dot3(centre, vec), dot3(vec, vec)
    return (cc * vv - t * t > r2 * vv) | ((t < 0) & (cc > r2))


def nearest_hits_kernel(m, d, groups: tuple[RayGroup, ...], pnt: jnp.ndarray, vecs: jnp.ndarray,
                        block: int = 128, interpret: bool = False):
    """`nearest_hit` for rays [R, 3] from one origin, as one Pallas kernel: each program takes
    `block` rays and runs every geom's test on them in turn, keeping the nearest hit, so that
    nothing but the rays and the result goes through memory. A geom with a bounding sphere
    (`geom_rbound` > 0, as MuJoCo C's ray caster uses it) is skipped by a program whose rays
    all miss that sphere, where its test would give inf to each of them: the hits are
    `nearest_hit`'s. They do not depend on `block`; 128 ran faster than 256 on an H100
    (BENCHMARKS.md). vmap adds the env axis to the grid. `interpret`: run the kernel's body
    as JAX operations (any backend; for tests)."""
    n_rays = vecs.shape[0]
    if not groups:
        return jnp.full((n_rays,), -1.0, jnp.float32), jnp.full((n_rays,), -1, jnp.int32)
    ids = np.concatenate([g.ids for g in groups])
    local_pnt = to_geom_frames(d.geom_xmat[ids], pnt - d.geom_xpos[ids])
    rbound = np.asarray(m.geom_rbound)
    table = jnp.concatenate([d.geom_xmat[ids].reshape(len(ids), 9), local_pnt, m.geom_size[ids],
                             d.geom_xpos[ids] - pnt], 1)
    table = table.astype(jnp.float32).reshape(-1)
    table = jnp.pad(table, (0, pl.next_power_of_2(table.size) - table.size))  # Triton blocks: powers of two
    padded = -(-n_rays // block) * block
    comps = [jnp.pad(vecs[:, i].astype(jnp.float32), (0, padded - n_rays)) for i in range(3)]

    def kernel(table_ref, vx_ref, vy_ref, vz_ref, dist_ref, gid_ref):
        vec = (vx_ref[...], vy_ref[...], vz_ref[...])
        best_dist = jnp.full(vec[0].shape, jnp.inf, jnp.float32)
        best_id = jnp.full(vec[0].shape, -1, jnp.int32)
        slot = 0
        for group in groups:
            for g in group.ids:
                row = [table_ref[_GEOM_ROW * slot + k] for k in range(_GEOM_ROW)]

                def test(row=row, test=group.test):
                    local_vec = [dot3(row[i::3][:3], vec) for i in range(3)]  # xmat^T vec, as to_geom_frames
                    return test(row[12:15], row[9:12], local_vec)

                if rbound[g] > 0:
                    all_miss = jnp.min(jnp.where(_misses_sphere(row[15:18], float(rbound[g]), vec), 1, 0)) == 1
                    dist = jax.lax.cond(all_miss, lambda: jnp.full(vec[0].shape, jnp.inf, jnp.float32), test)
                else:
                    dist = test()
                nearer = dist < best_dist  # strictly: the earlier geom keeps a tie, as in nearest_hit
                best_dist = jnp.where(nearer, dist, best_dist)
                best_id = jnp.where(nearer, jnp.int32(g), best_id)
                slot += 1
        miss = jnp.isinf(best_dist)
        dist_ref[...] = jnp.where(miss, -1.0, best_dist)
        gid_ref[...] = jnp.where(miss, -1, best_id)

    ray_block = pl.BlockSpec((block,), lambda i: (i,))
    call = pl.pallas_call(
        kernel, grid=(padded // block,),
        in_specs=[pl.BlockSpec((table.size,), lambda i: (0,)), ray_block, ray_block, ray_block],
        out_specs=[ray_block, ray_block],
        out_shape=[jax.ShapeDtypeStruct((padded,), jnp.float32), jax.ShapeDtypeStruct((padded,), jnp.int32)],
        # Triton, named: JAX's default GPU backend for Pallas is Mosaic GPU wherever it imports,
        # which takes no vmapped grid
        compiler_params=pltriton.CompilerParams(), interpret=interpret)
    dist, gid = per_device_batching(call)(table, *comps)
    return dist[:n_rays], gid[:n_rays]


def per_device_batching(fn):
    """`fn` whose batching (vmap) runs the vmapped `fn` on each device's share of the batch
    when a mesh is set for tracing (`jax.set_mesh`): the batch axis split over all of the
    mesh's axes, as the evaluator splits its envs. A kernel's call is opaque to XLA's
    partitioner (GSPMD), which would gather the whole batch onto every device and run all of
    it there. Without a mesh, with one device, or for a batch the mesh does not divide (a
    queue's resets), plain vmap."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        args = [x if batched else jnp.broadcast_to(x, (axis_size, *x.shape)) for x, batched in zip(args, in_batched)]
        batched = jax.vmap(fn)
        mesh = jax.sharding.get_abstract_mesh()
        if not mesh.empty and mesh.size > 1 and axis_size % mesh.size == 0:
            spec = jax.sharding.PartitionSpec(mesh.axis_names)
            batched = jax.shard_map(batched, in_specs=spec, out_specs=spec, check_vma=False)
        out = batched(*args)
        return out, jax.tree.map(lambda _: True, out)

    return wrapped
