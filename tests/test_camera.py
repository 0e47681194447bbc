"""The ray-cast camera: shape, object colours, and response to a moved object."""

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
