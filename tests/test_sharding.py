"""The batched evaluator sharded over 4 virtual CPU devices gives the unsharded results (6
episodes in 4 env slots, refilled as episodes end).

The device count is fixed when JAX starts, so each run is its own process (both on CPU,
started together: compiling the expert rollout dominates, ~2 min each on 2 cores)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow  # two processes, each compiling the expert rollout (~2 min each on 2 cores)
TASKS = ["left_block_plate", "pick_red_block"]

# Runs the expert on 3 episodes of each task in 4 parallel envs, prints the results as JSON.
SCRIPT = """
import json, sys
import envs  # XLA CPU flags before JAX starts
import jax
from envs import tasks
from envs.env import EnvConfig, TabletopEnv
from heisd_jax.harness import evaluator as ev, methods

env = TabletopEnv(tasks.get_tasks("all", sys.argv[1].split(",")), EnvConfig(render=False))
policy = methods.make_policy("expert", env)
out = {"devices": len(jax.devices())}
try:
    ev.BatchRollout(env, policy, num_envs=6)  # refused (4 devices) before anything is compiled
except ValueError as e:
    out["indivisible_error"] = str(e)
timing = []
out["results"] = ev.evaluate(env, policy, ev.EvalConfig(episodes_per_task=3, num_envs=4),
                             on_batch=lambda r, t: timing.append(t))
out["timing"] = timing
print("RESULT " + json.dumps(out))
"""


def _start(n_devices: int) -> subprocess.Popen:
    flags = os.environ.get("XLA_FLAGS", "")
    if n_devices > 1:
        flags += f" --xla_force_host_platform_device_count={n_devices}"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    return subprocess.Popen([sys.executable, "-c", SCRIPT, ",".join(TASKS)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, err[-3000:]
    (line,) = [l for l in out.splitlines() if l.startswith("RESULT ")]
    return json.loads(line[len("RESULT "):])


@pytest.fixture(scope="module")
def runs():
    procs = {n: _start(n) for n in (4, 1)}  # concurrently: compile time dominates
    try:
        return {n: _result(p) for n, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()


def test_sharded_evaluation_equals_unsharded(runs):
    sharded, single = runs[4], runs[1]
    assert sharded["devices"] == 4 and single["devices"] == 1
    assert [t["devices"] for t in sharded["timing"]] == [4] and [t["devices"] for t in single["timing"]] == [1]
    assert sorted(sharded["results"]) == TASKS
    for task in TASKS:
        assert len(sharded["results"][task]) == 3
        assert all(ep["steps"] > 0 for ep in sharded["results"][task])
    # success, steps, failure and decode totals of every episode
    assert sharded["results"] == single["results"]


def test_num_envs_not_divisible_by_device_count_is_refused(runs):
    assert "num_envs=6" in runs[4]["indivisible_error"] and "4 devices" in runs[4]["indivisible_error"]
    assert "indivisible_error" not in runs[1]  # one device takes any batch size
