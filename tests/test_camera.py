"""The ray-cast camera: shape, object colours, response to a moved object, and its ray caster
(`camera.cast`) against MJX's (`mjx.ray`); envs/raycast.py's tests are pinned in test_raycast.py."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from envs import camera, raycast, scene
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
    # rtol: where a ray grazes a capsule, its quadratic's discriminant cancels and amplifies the
    # rounding of the products, which the two casters order differently: both lie about 1e-5
    # from the float64 distance there
    np.testing.assert_allclose(np.asarray(d1), np.asarray(d0), rtol=5e-5)


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


def test_the_kernel_equals_cast_on_every_pixel_of_a_batch(rendered):
    """The GPU's caster (a Pallas kernel, run here by its interpreter) against `cast`, over two
    envs (vmap adds the env axis to the kernel's grid) and both views."""
    env, state, _ = rendered
    m = env.model
    data = jax.tree.map(lambda x: jnp.stack([x, x]), state.data)
    data = data.replace(geom_xpos=data.geom_xpos.at[1].add(0.01))  # the second env's geoms moved
    groups = raycast.ray_groups(m, camera.visible_geoms(m))
    for view in camera.VIEWS:
        cam = env.mj_model.camera(view)
        rays = jnp.asarray(camera.pixel_rays(64, 64, float(cam.fovy[0]))).reshape(-1, 3)

        def both(d):
            dirs = rays @ d.cam_xmat[cam.id].reshape(3, 3).T
            return (jax.vmap(lambda v: camera.cast(m, d, d.cam_xpos[cam.id], v))(dirs),
                    raycast.nearest_hits_kernel(m, d, groups, d.cam_xpos[cam.id], dirs, block=512, interpret=True))

        (d0, g0), (d1, g1) = jax.jit(jax.vmap(both))(data)
        assert len(np.unique(np.asarray(g0))) > 5
        np.testing.assert_array_equal(np.asarray(g1), np.asarray(g0))
        np.testing.assert_allclose(np.asarray(d1), np.asarray(d0), rtol=1e-6)
