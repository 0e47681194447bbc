"""The ray-cast camera: shape, object colours, response to a moved object, and its ray caster
(`camera.cast`) against MJX's (`mjx.ray`) and a triangle-by-triangle mesh test."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from envs import camera, scene
from envs.env import EnvConfig, TabletopEnv


@pytest.fixture(scope="module")
def rendered():
    env = TabletopEnv(config=EnvConfig(render=True))
    state = jax.jit(env.reset)(env.initial_state_keys([0], [0])[0], 0)
    cam = env.config.camera
    render = jax.jit(lambda d, rgb: camera.render_views(env.mj_model, env.model, d, rgb, cam))
    return env, state, render


def _chroma_mask(img, rgb, tol=0.06):
    """Pixels whose chromaticity (colour up to brightness) matches `rgb`."""
    x = img.astype(np.float64)
    c = x / np.maximum(x.sum(-1, keepdims=True), 1)
    want = np.asarray(rgb) / np.sum(rgb)
    return (np.abs(c - want).max(-1) < tol) & (x.sum(-1) > 60)


def _forward_on_host(env, data, qpos):
    """`data` at `qpos` with the poses that follow from it, computed by MuJoCo's forward on
    the host (an eager mjx.forward takes over a minute on CPU, compiling it most of one)."""
    d = mjx.get_data(env.mj_model, data)
    d.qpos[:] = np.asarray(qpos)
    mujoco.mj_forward(env.mj_model, d)
    fields = ("xpos", "xmat", "xquat", "geom_xpos", "geom_xmat", "site_xpos", "site_xmat", "cam_xpos", "cam_xmat")
    return data.replace(qpos=qpos, **{f: jnp.asarray(getattr(d, f), getattr(data, f).dtype).reshape(getattr(data, f).shape)
                                      for f in fields})


def test_image_shape_and_dtype(rendered):
    env, state, _ = rendered
    assert state.obs.image.shape == (64, 64, 3) and state.obs.image.dtype == jnp.uint8
    assert np.asarray(state.obs.image).std() > 10  # not a blank frame


def test_each_object_shows_its_colour(rendered):
    env, state, render = rendered
    img = np.asarray(state.obs.image)
    colors = np.asarray(state.info.colors)
    for slot, c in enumerate(colors):
        rgb = scene.PALETTE[scene.COLOR_NAMES[c]]
        assert _chroma_mask(img, rgb).sum() >= 4, (slot, scene.COLOR_NAMES[c])
    # Recolouring an object (a render input, not a model change) recolours its pixels.
    new = state.info.replace(colors=jnp.asarray(colors).at[0].set((colors[0] + 1) % len(scene.COLOR_NAMES)))
    img2 = np.asarray(render(state.data, env.geom_colors(new)))
    assert not np.array_equal(img, img2)


def test_image_changes_when_an_object_moves(rendered):
    env, state, render = rendered
    img = np.asarray(render(state.data, env.geom_colors(state.info)))
    np.testing.assert_array_equal(img, state.obs.image)  # rendering is deterministic
    slot = 0
    rgb = scene.PALETTE[scene.COLOR_NAMES[int(state.info.colors[slot])]]
    before = _chroma_mask(img, rgb)
    adr = env.ids.object_qpos[slot]
    qpos = state.data.qpos.at[adr + 1].add(0.12)  # slide it 12 cm sideways
    moved = _forward_on_host(env, state.data, qpos)
    img2 = np.asarray(render(moved, env.geom_colors(state.info)))
    after = _chroma_mask(img2, rgb)
    assert after.sum() >= 4
    # The object's pixels moved: its colour mask no longer overlaps its old place much.
    assert (before & after).sum() < 0.5 * before.sum()


def _cube_mesh():
    """(vert, face) of a unit cube as MuJoCo triangulates it (12 triangles)."""
    corners = " ".join(f"{x} {y} {z}" for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5))
    m = mujoco.MjModel.from_xml_string(f'<mujoco><asset><mesh name="c" vertex="{corners}"/></asset>'
                                       f'<worldbody><geom type="mesh" mesh="c"/></worldbody></mujoco>')
    return m.mesh_vert.copy(), m.mesh_face.copy()


def test_convex_ray_equals_the_nearest_triangle_hit():
    from mujoco.mjx._src import ray as mjx_ray  # noqa: PLC0415

    vert, face = _cube_mesh()
    normals, offsets = camera.mesh_planes(vert, face)
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
    got = np.asarray(jax.vmap(lambda p, v: camera._ray_convex(normals, offsets, p, v))(pnts, vecs))
    assert np.isfinite(want).sum() > 100 and np.isinf(want).sum() > 100  # hits and misses both tested
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], rtol=1e-5, atol=1e-6)


def test_mesh_planes_refuses_a_non_convex_mesh():
    vert, face = _cube_mesh()
    vert[0] *= 0.2  # a corner pushed inside: the faces around it fold inwards
    with pytest.raises(ValueError, match="convex mesh"):
        camera.mesh_planes(vert, face)


def test_cast_agrees_with_mjx_ray_on_every_pixel(rendered):
    env, state, _ = rendered
    m, d = env.model, state.data
    cam = env.mj_model.camera(camera.VIEWS[0])
    origin = d.cam_xpos[cam.id]
    dirs = jnp.asarray(camera.pixel_rays(64, 64, float(cam.fovy[0]))).reshape(-1, 3) @ d.cam_xmat[cam.id].reshape(3, 3).T
    groups = tuple(int(g in camera.VISIBLE_GROUPS) for g in range(mujoco.mjNGROUP))
    d0, g0 = jax.jit(jax.vmap(lambda v: mjx.ray(m, d, origin, v, geomgroup=groups)))(dirs)
    d1, g1 = jax.jit(jax.vmap(lambda v: camera.cast(m, d, origin, v)))(dirs)
    meshes = np.flatnonzero(env.mj_model.geom_type == mujoco.mjtGeom.mjGEOM_MESH)
    assert np.isin(np.asarray(g0), meshes).sum() > 10  # the cylinders are in view
    np.testing.assert_array_equal(np.asarray(g1), np.asarray(g0))
    np.testing.assert_allclose(np.asarray(d1), np.asarray(d0), rtol=1e-5)


def test_view_geoms_lists_what_the_pixels_show_and_respects_transparency(rendered):
    env, state, _ = rendered
    mj, cfg = env.mj_model, env.config.camera
    table, pad = (mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("table", "pad_left"))
    seen = np.asarray(jax.jit(lambda d: camera.view_geoms(mj, env.model, d, cfg))(state.data))
    assert seen.shape == (len(cfg.views), mj.ngeom) and seen[:, table].all() and seen[:, pad].any()
    rgba = np.asarray(env.model.mat_rgba).copy()
    rgba[mj.geom_matid[pad], 3] = 0.0  # the finger pads' material made transparent: never hit
    m = env.model.replace(mat_rgba=rgba)  # the model is a constant of the program: cast reads its visibility
    hidden = np.asarray(jax.jit(lambda d: camera.view_geoms(mj, m, d, cfg))(state.data))
    assert not hidden[:, pad].any() and hidden[:, table].all()
