"""Data-parallel training (`training.make_train_step(..., mesh)`, `make_drafter_step`): steps
over 2 devices give the single-device steps' loss and update, up to the gradient's
summation order, and a batch the devices cannot split evenly is refused by name.

The device count is fixed when JAX starts, so the comparison runs in its own process with
2 forced CPU devices."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import json
import envs  # XLA CPU flags before JAX starts
import jax, jax.numpy as jnp, numpy as np
from heisd_jax import sharding, vla
from heisd_jax.harness import data, training
from heisd_jax.tokenizer import ActionTokenizer

cfg = vla.VLAConfig(image_size=16, patch_size=8, vision_layers=1, d_model=32, n_layers=2, n_heads=4, mlp_dim=64,
                    cache_slots=48)
rng = np.random.default_rng(0)
n = 64
table = data.StepTable(image=rng.integers(0, 255, (n, 16, 16, 3), dtype=np.uint8),
                       proprio=rng.normal(size=(n, 8)).astype(np.float32),
                       instruction=rng.integers(1, cfg.text_vocab, (n, cfg.text_len)).astype(np.int32),
                       action=np.tanh(rng.normal(size=(n, 7))).astype(np.float32))
tok = ActionTokenizer.fit(table.action, cfg.vocab_size)
tcfg = training.TrainConfig(steps=10, batch_size=8, lr=1e-2, warmup_steps=1, image_shift=2)
mesh = sharding.env_mesh()
whole = sharding.replicate
key = jax.random.PRNGKey(3)
out = {"devices": mesh.size}

def compare(name, single, parallel, key_name=None):
    (s1, m1), (s2, m2) = single, parallel
    p1, p2 = jax.tree.leaves(s1.params), jax.tree.leaves(s2.params)
    d0 = jax.tree.leaves(state0(name).params)
    out[key_name or name] = {"loss": [float(m1["loss"]), float(m2["loss"])],
                 "max_param_diff": max(float(jnp.abs(a - b).max()) for a, b in zip(p1, p2)),
                 "max_update": max(float(jnp.abs(a - b).max()) for a, b in zip(p1, d0)),
                 "param_diff": sum(float(jnp.abs(a - b).sum()) for a, b in zip(p1, p2)),
                 "update": sum(float(jnp.abs(a - b).sum()) for a, b in zip(p1, d0)),
                 "sharded_over": len(p2[0].sharding.device_set)}

def state0(name):
    return training.init_state(cfg, tcfg) if name == "vla" else training.init_drafter_state(cfg, tcfg)

def twice(step, state, *args):  # the schedule's first step has a learning rate of 0
    state, _ = step(state, *args)
    return step(state, *args)

t_single, t_mesh = jax.device_put(table), whole(mesh, table)
step1, stepm = training.make_train_step(cfg, tcfg, tok), training.make_train_step(cfg, tcfg, tok, mesh)
compare("vla", twice(step1, state0("vla"), t_single, key), twice(stepm, whole(mesh, state0("vla")), t_mesh, key))

# A table drawn by row weights (train --weights_from): the mesh draws the same rows.
weighted = data.with_row_weights(table, rng.integers(1, 5, n))
t_single, t_mesh = jax.device_put(weighted), whole(mesh, weighted)
compare("vla", twice(step1, state0("vla"), t_single, key), twice(stepm, whole(mesh, state0("vla")), t_mesh, key),
        "vla_weighted")
t_single, t_mesh = jax.device_put(table), whole(mesh, table)

tparams = state0("vla").params
labels = tok.to_ids(table.action)
d1, dm = training.make_drafter_step(cfg, tcfg), training.make_drafter_step(cfg, tcfg, mesh)
compare("drafter", twice(d1, state0("drafter"), tparams, t_single, labels, key),
        twice(dm, whole(mesh, state0("drafter")), whole(mesh, tparams), t_mesh, whole(mesh, labels), key))
try:
    training.make_train_step(cfg, training.TrainConfig(steps=10, batch_size=7, warmup_steps=1), tok, mesh)
except ValueError as e:
    out["indivisible"] = str(e)
print("RESULT " + json.dumps(out))
"""


@pytest.fixture(scope="module")
def two_devices():
    env = {**os.environ, "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"),
           "JAX_PLATFORMS": "cpu"}
    run = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=900)
    line = next((x for x in run.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line, run.stdout[-2000:] + run.stderr[-4000:]
    return json.loads(line[len("RESULT "):])


@pytest.mark.parametrize("model", ["vla", "vla_weighted", "drafter"])
def test_a_data_parallel_step_equals_the_single_device_step(two_devices, model):
    assert two_devices["devices"] == 2
    r = two_devices[model]
    assert r["sharded_over"] == 2  # the state lives on both devices
    assert r["loss"][0] == pytest.approx(r["loss"][1], rel=1e-5)
    assert r["max_update"] > 1e-4  # the step moved the parameters ...
    # ... and both steps moved them alike: the gradients differ in summation order only,
    # which Adam's normalisation can magnify for a parameter whose gradient is ~0
    assert r["param_diff"] < 1e-3 * r["update"]
    assert r["max_param_diff"] < 0.05 * r["max_update"]
    if model == "vla_weighted":  # the weights reached the draw: other rows, another loss
        assert r["loss"][0] != two_devices["vla"]["loss"][0]


def test_a_batch_the_devices_cannot_split_is_refused(two_devices):
    assert two_devices["indivisible"] == ("batch_size 7 is not divisible by the 2 devices it is split over; "
                                          "use a multiple of 2")
