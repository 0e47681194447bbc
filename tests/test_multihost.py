"""Several hosts: two processes joined by `jax.distributed` on localhost (CPU, JAX's gloo
collectives), one CPU device each, run one evaluation together, each stepping its own half
of every env batch, and both get the per-episode results of a single-process run.

Each run is its own process (the device set is fixed when JAX starts); all three start
together since compiling the expert rollout dominates (minutes each on 2 cores)."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TASKS = ["left_block_plate", "pick_red_block"]
EPISODES, NUM_ENVS = 3, 4  # 6 episodes: a full batch, then a padded one

# argv: processes, process id, coordinator port. Prints the results as JSON.
SCRIPT = """
import json, sys
import envs  # XLA CPU flags before JAX starts
import jax
import numpy as np
from experiments import cli

n, pid, port = map(int, sys.argv[1:4])
if n > 1:
    cli.setup_distributed(f"localhost:{port}", num_processes=n, process_id=pid)
from envs import expert, tasks
from envs.env import EnvConfig, TabletopEnv
from heisd_jax.harness import evaluator as ev

env = TabletopEnv(tasks.get_tasks("all", sys.argv[4].split(",")), EnvConfig(render=False))
policy = expert.policy(env)
cfg = ev.EvalConfig(episodes_per_task=int(sys.argv[5]), num_envs=int(sys.argv[6]), refill=False)  # as several processes run
run = ev.BatchRollout(env, policy, cfg.num_envs)
_, keys, _, _ = run.inputs(np.zeros(cfg.num_envs, int), np.arange(cfg.num_envs) % cfg.episodes_per_task)
timing = []
results = ev.evaluate(env, policy, cfg, on_batch=lambda r, t: timing.append(t))
print("RESULT " + json.dumps({"process": jax.process_index(), "processes": jax.process_count(),
                              "devices": len(jax.devices()), "local_devices": len(jax.local_devices()),
                              "local_rows": [s.data.shape[0] for s in keys.addressable_shards],
                              "results": results, "timing": timing}))
"""




def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _start(n: int, pid: int, port: int) -> subprocess.Popen:
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split()
                     if not f.startswith("--xla_force_host_platform_device_count"))
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    argv = [str(n), str(pid), str(port), ",".join(TASKS), str(EPISODES), str(NUM_ENVS)]
    return subprocess.Popen([sys.executable, "-c", SCRIPT, *argv], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=1500)
    assert proc.returncode == 0, err[-3000:]
    (line,) = [l for l in out.splitlines() if l.startswith("RESULT ")]
    return json.loads(line[len("RESULT "):])


@pytest.fixture(scope="module")
def runs():
    port = _free_port()
    procs = {"host0": _start(2, 0, port), "host1": _start(2, 1, port), "single": _start(1, 0, 0)}
    try:
        return {k: _result(p) for k, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()


@pytest.mark.slow
def test_each_process_owns_half_of_the_env_batch(runs):
    for pid, key in enumerate(("host0", "host1")):
        r = runs[key]
        assert (r["process"], r["processes"], r["devices"], r["local_devices"]) == (pid, 2, 2, 1)
        assert r["local_rows"] == [NUM_ENVS // 2]
        assert [t["devices"] for t in r["timing"]] == [2, 2]
    assert runs["single"]["processes"] == 1 and [t["devices"] for t in runs["single"]["timing"]] == [1, 1]


@pytest.mark.slow
def test_two_processes_give_the_single_process_results(runs):
    single = runs["single"]["results"]
    assert sorted(single) == TASKS and all(len(single[t]) == EPISODES for t in TASKS)
    assert all(ep["steps"] > 0 for t in TASKS for ep in single[t])
    # success, steps, failure and decode totals of every episode, gathered on both processes
    assert runs["host0"]["results"] == single
    assert runs["host1"]["results"] == single


# An entry point: cli.run joins the processes from the flags before main touches a device.
CLI_SCRIPT = """
import jax, jax.numpy as jnp
from experiments import cli
def main(argv):
    jax.jit(lambda: jnp.zeros(()))().block_until_ready()
    print("RESULT", jax.process_index(), jax.process_count(), len(jax.devices()))
cli.run(main)
"""


def test_entry_points_join_from_the_flags():
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    procs = [subprocess.Popen([sys.executable, "-c", CLI_SCRIPT, f"--coordinator_address=localhost:{port}",
                               "--num_processes=2", f"--process_id={i}", "--compilation_cache="],
                              cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    try:
        outs = [p.communicate(timeout=300) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for i, (p, (out, err)) in enumerate(zip(procs, outs)):
        assert p.returncode == 0, err[-2000:]
        assert f"RESULT {i} 2 2" in out
