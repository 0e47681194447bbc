"""envs.raycast: each geom type's ray test against MJX's, the convex mesh test against the
nearest triangle hit, the reduction that keeps a ray's nearest geom, and the camera kernel's
batch split over the devices of a mesh."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import ray as mjx_ray

from envs import raycast


def _rays(n, seed, spread=1.5):
    """n rays from points around the origin aimed near it (hits and misses), with some
    parallel to the axes, as float32."""
    rng = np.random.default_rng(seed)
    pnts = rng.uniform(-spread, spread, (n, 3)).astype(np.float32)
    vecs = (rng.uniform(-0.8, 0.8, (n, 3)) - pnts).astype(np.float32)
    vecs[: n // 10] = np.array([0, 0, -1], np.float32)
    vecs[n // 10: n // 5] = np.array([1, 0, 0], np.float32)
    return pnts, vecs / np.linalg.norm(vecs, axis=1, keepdims=True)


SHAPES = {  # geom type: (raycast's test, MJX's, size)
    "plane": (raycast.ray_plane, mjx_ray._ray_plane, [0.6, 0.4, 0.01]),
    "infinite plane": (raycast.ray_plane, mjx_ray._ray_plane, [0.0, 0.0, 0.01]),
    "sphere": (raycast.ray_sphere, mjx_ray._ray_sphere, [0.5, 0, 0]),
    "capsule": (raycast.ray_capsule, mjx_ray._ray_capsule, [0.3, 0.5, 0]),
    "ellipsoid": (raycast.ray_ellipsoid, mjx_ray._ray_ellipsoid, [0.3, 0.5, 0.7]),
    "box": (raycast.ray_box, mjx_ray._ray_box, [0.3, 0.5, 0.7]),
}


@pytest.mark.parametrize("shape", list(SHAPES))
def test_each_test_equals_mjx(shape):
    ours, theirs, size = SHAPES[shape]
    pnts, vecs = _rays(600, 1)
    size = jnp.asarray(size, jnp.float32)
    got = np.asarray(jax.jit(jax.vmap(lambda p, v: ours(size, p, v)))(pnts, vecs))
    want = np.asarray(jax.jit(jax.vmap(lambda p, v: theirs(size, p, v)))(pnts, vecs))
    assert np.isfinite(want).sum() > 50 and np.isinf(want).sum() > 50  # hits and misses both tested
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], rtol=1e-5, atol=1e-6)


def test_tests_hold_no_dot_or_reduction():
    """The component form that lets a Pallas kernel run the tests on a block of rays."""
    pnts, vecs = _rays(8, 2)
    for shape, (ours, _, size) in SHAPES.items():
        hlo = jax.jit(jax.vmap(lambda p, v: ours(jnp.asarray(size, jnp.float32), p, v))).lower(pnts, vecs).as_text()
        assert "dot_general" not in hlo and "reduce" not in hlo, shape
    normals, offsets = raycast.mesh_planes(*_cube_mesh())
    hlo = jax.jit(jax.vmap(lambda p, v: raycast.ray_convex(normals, offsets, p, v))).lower(pnts, vecs).as_text()
    assert "dot_general" not in hlo and "reduce" not in hlo


def test_first_min_is_min_and_argmin_ties_included():
    rng = np.random.default_rng(3)
    d = rng.integers(0, 4, (50, 7)).astype(np.float32)  # many ties
    d[:5] = np.inf  # rows with no hit
    d[5:10, 2:] = np.inf
    dist, i = jax.jit(raycast.first_min)(jnp.asarray(d))
    np.testing.assert_array_equal(np.asarray(dist), d.min(1))
    np.testing.assert_array_equal(np.asarray(i)[5:], d.argmin(1)[5:])
    assert np.asarray(i).dtype == np.int32


def _cube_mesh():
    """(vert, face) of a unit cube as MuJoCo triangulates it (12 triangles)."""
    corners = " ".join(f"{x} {y} {z}" for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5))
    m = mujoco.MjModel.from_xml_string(f'<mujoco><asset><mesh name="c" vertex="{corners}"/></asset>'
                                       f'<worldbody><geom type="mesh" mesh="c"/></worldbody></mujoco>')
    return m.mesh_vert.copy(), m.mesh_face.copy()


def test_convex_ray_equals_the_nearest_triangle_hit():
    vert, face = _cube_mesh()
    normals, offsets = raycast.mesh_planes(vert, face)
    assert len(face) == 12 and len(normals) == 6  # coplanar triangles share a plane
    rng = np.random.default_rng(0)
    pnts = rng.uniform(-1.5, 1.5, (400, 3)).astype(np.float32)  # some inside the cube
    vecs = (rng.uniform(-0.8, 0.8, (400, 3)) - pnts).astype(np.float32)  # aimed near the cube: hits and misses
    vecs[:40] = np.array([0, 0, -1], np.float32)  # axis-parallel rays: parallel to four planes
    vecs /= np.linalg.norm(vecs, axis=1, keepdims=True)
    tris = jnp.asarray(vert[face])

    def triangles(p, v):
        basis = jnp.array(mjx_ray.math.orthogonals(v)).T
        return jnp.min(jax.vmap(mjx_ray._ray_triangle, in_axes=(0, None, None, None))(tris, p, v, basis))

    want = np.asarray(jax.vmap(triangles)(pnts, vecs))
    got = np.asarray(jax.vmap(lambda p, v: raycast.ray_convex(normals, offsets, p, v))(pnts, vecs))
    assert np.isfinite(want).sum() > 100 and np.isinf(want).sum() > 100  # hits and misses both tested
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], rtol=1e-5, atol=1e-6)


def test_mesh_planes_refuses_a_non_convex_mesh():
    vert, face = _cube_mesh()
    vert[0] *= 0.2  # a corner pushed inside: the faces around it fold inwards
    with pytest.raises(ValueError, match="convex mesh"):
        raycast.mesh_planes(vert, face)




def test_casters_without_visible_geoms_miss_every_ray():
    mj = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom type="sphere" size="0.1" group="3"/>'
                                        '</worldbody></mujoco>')
    m, d = mjx.put_model(mj), mjx.make_data(mj)
    groups = raycast.ray_groups(m, np.zeros(mj.ngeom, bool))
    vecs = jnp.asarray(_rays(4, 3)[1])
    for dist, gid in (jax.vmap(lambda v: raycast.nearest_hit(m, d, groups, jnp.zeros(3), v))(vecs),
                      raycast.nearest_hits_kernel(m, d, groups, jnp.zeros(3), vecs, interpret=True)):
        np.testing.assert_array_equal(np.asarray(dist), -1.0)
        np.testing.assert_array_equal(np.asarray(gid), -1)


def test_the_kernels_cull_test_never_drops_a_hit():
    """`_misses_sphere` (which lets a kernel program skip a geom) only where the sphere's own
    ray test misses too, rays grazing the sphere and starting inside it included."""
    rng = np.random.default_rng(4)
    centres = rng.uniform(-1, 1, (4000, 3)).astype(np.float32)
    radii = rng.uniform(0.01, 0.3, 4000).astype(np.float32)
    vecs = rng.normal(size=(4000, 3)).astype(np.float32)
    vecs /= np.linalg.norm(vecs, axis=1, keepdims=True)
    # a third aimed at the sphere's rim: the line passes at distance radius * (1 +- 1e-4)
    side = np.cross(vecs[:1333], rng.normal(size=(1333, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    rim = radii[:1333, None] * (1 + rng.uniform(-1e-4, 1e-4, (1333, 1))) * side
    centres[:1333] = (rim + vecs[:1333] * rng.uniform(0.2, 1.5, (1333, 1))).astype(np.float32)
    culled = np.array([bool(raycast._misses_sphere(c, float(r), v)) for c, r, v in zip(centres, radii, vecs)])
    hits = np.isfinite(np.asarray(jax.vmap(lambda c, r, v: raycast.ray_sphere(jnp.stack([r, 0, 0]), -c, v))(
        jnp.asarray(centres), jnp.asarray(radii), jnp.asarray(vecs))))
    assert culled.sum() > 1000 and hits.sum() > 500
    assert not (culled & hits).any()


# The camera kernel (by its interpreter) over 4 envs on 2 virtual CPU devices: without a mesh,
# GSPMD gathers the batch onto each device; under `jax.set_mesh` each device casts its own envs.
_SHARDED_SCRIPT = """
import json
import envs  # XLA CPU flags before JAX starts
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from envs import camera, raycast, tasks
from envs.env import EnvConfig, TabletopEnv

env = TabletopEnv(tasks.get_tasks("all", ["pick_red_block"]), EnvConfig(render=False))
m, cam = env.model, env.mj_model.camera("agentview")
ids = np.zeros(4, np.int32)
d = jax.jit(jax.vmap(env.reset))(env.initial_state_keys(ids, np.arange(4)), jnp.asarray(ids)).data
groups = raycast.ray_groups(m, camera.visible_geoms(m))
rays = jnp.asarray(camera.pixel_rays(16, 16, float(cam.fovy[0]))).reshape(-1, 3)

def hits(d):  # the rays turned with each env's camera (batched) and as they are (not batched)
    turned = rays @ d.cam_xmat[cam.id].reshape(3, 3).T
    return [raycast.nearest_hits_kernel(m, d, groups, d.cam_xpos[cam.id], v, block=256, interpret=True)
            for v in (turned, rays)]

def same(a, b):  # the same hits; distances up to float rounding (the rays' rotation is a matmul
    a, b = np.asarray(a), np.asarray(b)   # whose summation order XLA:CPU may pick per batch layout)
    return bool((a == b).all()) if a.dtype.kind == "i" else bool(np.allclose(a, b, rtol=0, atol=1e-5))

want = jax.jit(jax.vmap(hits))(d)
mesh = Mesh(np.asarray(jax.devices()), ("envs",))
split = jax.device_put(d, NamedSharding(mesh, P("envs")))
out = {"devices": jax.device_count()}
for name in ("no mesh", "mesh"):
    fn = jax.jit(jax.vmap(hits))
    if name == "mesh":
        with jax.set_mesh(mesh):
            compiled = fn.trace(split).lower().compile()
    else:
        compiled = fn.trace(split).lower().compile()
    got = compiled(split)
    out[name] = {"all_gather": "all-gather" in compiled.as_text(),
                 "equal": all(same(a, b) for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want))),
                 "split_output": not got[0][1].sharding.is_fully_replicated}
odd = jax.tree.map(lambda x: x[:3], d)  # 3 envs: the mesh does not divide them
with jax.set_mesh(mesh):
    got = jax.jit(jax.vmap(hits))(odd)
out["3 envs"] = all(same(a, np.asarray(b)[:3]) for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)))
print("RESULT " + json.dumps(out))
"""


def test_the_kernel_splits_its_batch_over_the_devices_of_a_mesh():
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    proc = subprocess.run([sys.executable, "-c", _SHARDED_SCRIPT], cwd=Path(__file__).resolve().parents[1],
                          env=dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu"),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (line,) = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    out = json.loads(line[len("RESULT "):])
    assert out["devices"] == 2
    assert out["no mesh"] == {"all_gather": True, "equal": True, "split_output": False}  # what the rule avoids
    assert out["mesh"] == {"all_gather": False, "equal": True, "split_output": True}
    assert out["3 envs"]  # a batch the mesh does not divide: plain vmap, the same hits
