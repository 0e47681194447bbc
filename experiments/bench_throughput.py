"""Policy-in-the-loop evaluation throughput: the batched evaluator vs a sequential
per-episode loop, in one run.

  python -m experiments.bench_throughput --method=expert --suites=spatial --batch_sizes=1,64,256,1024 \
      --episodes=1024 --seq_episodes=16 --out=results/bench_throughput.json

Scaling over devices: a batch size written B:D shards B envs over the first D local devices
(plain B: the most local devices that divide B), so --batch_sizes=1024:1,1024:2,2048:2 times
one and two devices in the same run and prints each row's ratio to the one-device row of the
same batch size.

--compile_only compiles every program of the run (the sequential loop's by playing its
warm-up episode, each batch size's rollout ahead of time) and times nothing: with
JAX_COMPILATION_CACHE_DIR set, several such processes can compile at once on a many-core
host, and the timed run then loads its programs from that cache.

Batched: `heisd_jax.harness.evaluator.BatchRollout`, the evaluator's jitted rollout (one
`lax.while_loop` over control steps, envs vmapped and sharded over the devices), running
at least --episodes episodes per batch size in whole batches. Sequential: what LIBERO-style
evaluation does: one env, and per control step one jitted policy call and one jitted env
step dispatched from Python, the episode's end checked on the host. Episodes cycle over
the tasks and their fixed evaluation initial states; both modes use the same policy keys,
so a deterministic policy plays the same episodes in both. Compilation and one warm-up
call are excluded from every timing. Episodes per second, and the ratio to the sequential
loop, are printed per batch size.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import results_io, sharding
from heisd_jax.harness import evaluator as ev, methods
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_enum("method", "expert", sorted(methods.METHODS), "Decoding method (policy) in the loop.")
flags.DEFINE_string("suites", "spatial", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names (default: every task of the suites).")
flags.DEFINE_list("batch_sizes", ["1", "64", "256", "1024"],
                  "Parallel env counts of the batched evaluator, each B or B:D (B envs sharded over the "
                  "first D local devices; plain B: the most local devices that divide B).")
flags.DEFINE_integer("episodes", 1024, "Episodes timed per batch size (rounded up to whole batches).")
flags.DEFINE_integer("seq_episodes", 16, "Episodes timed in the sequential loop.")
cli.define_paths("checkpoint", "drafter")
flags.DEFINE_string("out", "", "Optional JSON output path.")
flags.DEFINE_bool("compile_only", False, "Compile the run's programs (fills JAX_COMPILATION_CACHE_DIR), time nothing.")


def episode_list(env: TabletopEnv, n: int) -> np.ndarray:
    """[n, 2] (task index, initial state) pairs, cycling over tasks, then initial states."""
    i = np.arange(n)
    return np.stack([i % len(env.tasks), (i // len(env.tasks)) % tasks_lib.N_EVAL_INIT_STATES], 1)


def outcome(final, i: int) -> tuple[bool, int]:
    return bool(final.success[i]), int(final.step[i])


def batched(env: TabletopEnv, policy: rollout.Policy, batch: int, n_episodes: int, n_dev: int,
            compile_only: bool = False) -> dict:
    """Episodes per second of the batched evaluator's rollout at `batch` envs over the
    first `n_dev` local devices (compile_only: compile it, time nothing, return {})."""
    run = ev.BatchRollout(env, policy, batch, devices=jax.local_devices()[:n_dev])
    eps = episode_list(env, math.ceil(n_episodes / batch) * batch)
    if compile_only:
        run.compile(run.inputs(*eps[:batch].T))
        return {}
    run(run.inputs(*eps[:batch].T))  # compile + warm-up
    outcomes = []
    t0 = time.perf_counter()
    for start in range(0, len(eps), batch):
        out, _ = run(run.inputs(*eps[start: start + batch].T))
        outcomes += [(bool(out.success[i]), int(out.steps[i])) for i in range(batch)]
    dt = time.perf_counter() - t0
    return {"mode": "batched", "num_envs": batch, "devices": n_dev, "episodes": len(eps), "seconds": dt,
            "episodes_per_s": len(eps) / dt, "compile_s": run.compile_seconds, "outcomes": outcomes}


def sequential(env: TabletopEnv, policy: rollout.Policy, n_episodes: int, compile_only: bool = False) -> dict:
    """Episodes per second of a per-episode loop: one env, one jitted policy call and one
    jitted env step per control step from Python (LIBERO-style). Its compile_s includes the
    warm-up episode."""
    max_steps = int(max(t.max_steps for t in env.tasks))
    start = jax.jit(lambda params, k, t: rollout._start(env, dataclasses.replace(policy, params=params), k, t))
    act = jax.jit(lambda params, s, ps, ak, t: rollout._act(dataclasses.replace(policy, params=params), s, ps, ak, t))
    step = jax.jit(jax.vmap(env.step))
    eps = episode_list(env, n_episodes)

    def episode(tid: int, ep: int):
        keys = env.initial_state_keys([tid], [ep])  # [1, 2]
        state, pstate, act_keys = start(policy.params, keys, jnp.asarray([tid], jnp.int32))
        for t in range(max_steps):
            action, pstate, _ = act(policy.params, state, pstate, act_keys, jnp.asarray(t, jnp.int32))
            state = step(state, action)
            if bool(state.done[0]):
                break
        return outcome(jax.device_get(state), 0)

    t0 = time.perf_counter()
    episode(*eps[0])  # compile + warm-up
    compile_s = time.perf_counter() - t0
    if compile_only:
        return {}
    t0 = time.perf_counter()
    outcomes = [episode(*e) for e in eps]
    dt = time.perf_counter() - t0
    return {"mode": "sequential", "num_envs": 1, "devices": 1, "episodes": n_episodes, "seconds": dt,
            "episodes_per_s": n_episodes / dt, "compile_s": compile_s, "outcomes": outcomes}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    task_list = cli.task_list(FLAGS.suites, FLAGS.tasks)  # every bad value is reported before anything is compiled
    try:
        sizes = sharding.parse_batch_devices(FLAGS.batch_sizes, jax.local_device_count())
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if not sizes:
        raise app.UsageError("--batch_sizes is empty")
    if FLAGS.episodes < 1 or FLAGS.seq_episodes < 1:
        raise app.UsageError("--episodes and --seq_episodes must be >= 1")
    env = TabletopEnv(task_list, methods.env_config(FLAGS.method, FLAGS.checkpoint))
    policy = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter)
    device = f"{jax.devices()[0].device_kind} x{jax.device_count()}"
    print(f"{FLAGS.method} on {len(task_list)} tasks, {device}, jax {jax.__version__}", flush=True)

    settings = {k: FLAGS[k].value
                for k in ("method", "suites", "tasks", "batch_sizes", "episodes", "seq_episodes")}
    rows = []

    def add(row: dict) -> None:
        """Ratios against the sequential loop (rows[0]), then the JSON rewritten: an interrupted
        run keeps every finished row."""
        base = rows[0] if rows else row
        row["x_sequential"] = row["episodes_per_s"] / base["episodes_per_s"]
        row["success_rate"] = float(np.mean([s for s, _ in row["outcomes"]]))
        # Episodes also played by the sequential loop (same initial state and policy keys).
        row["same_of"] = min(len(row["outcomes"]), len(base["outcomes"]))
        row["same_as_sequential"] = sum(a == b for a, b in zip(row["outcomes"], base["outcomes"][:row["same_of"]]))
        one = [r for r in rows if r["mode"] == "batched" and r["num_envs"] == row["num_envs"] and r["devices"] == 1]
        row["x_one_device"] = row["episodes_per_s"] / one[0]["episodes_per_s"] if one else None
        rows.append(row)
        label = ("sequential" if row["mode"] == "sequential"
                 else f"batched {row['num_envs']} on {row['devices']} device(s)")
        scale = f", {row['x_one_device']:.2f}x one device" if row["x_one_device"] and row["devices"] > 1 else ""
        print(f"  {label}: {row['episodes_per_s']:.3f} episodes/s ({row['x_sequential']:.2f}x sequential{scale})",
              flush=True)
        if FLAGS.out:
            results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()),
                                                      "settings": settings, "device": device, "jax": jax.__version__,
                                                      "tasks": [t.name for t in task_list], "rows": rows})

    if FLAGS.compile_only:
        sequential(env, policy, FLAGS.seq_episodes, compile_only=True)
        for b, d in sizes:
            batched(env, policy, b, FLAGS.episodes, d, compile_only=True)
        print("compiled; nothing timed (--compile_only)")
        return
    add(sequential(env, policy, FLAGS.seq_episodes))
    for b, d in sizes:
        add(batched(env, policy, b, FLAGS.episodes, d))

    print(f"\n{'mode':<12}{'envs':>6}{'devices':>9}{'episodes':>10}{'episodes/s':>12}{'x sequential':>14}"
          f"{'x 1 device':>12}{'success':>9}{'compile s':>11}")
    for r in rows:
        scale = f"{r['x_one_device']:.2f}" if r["x_one_device"] else "-"
        print(f"{r['mode']:<12}{r['num_envs']:>6}{r['devices']:>9}{r['episodes']:>10}{r['episodes_per_s']:>12.3f}"
              f"{r['x_sequential']:>14.2f}{scale:>12}{r['success_rate']:>9.3f}{r['compile_s']:>11.0f}")
    same = ", ".join(f"{r['same_as_sequential']}/{r['same_of']}" for r in rows[1:])
    print(f"episodes identical to the sequential loop's (success, steps), per batch size: {same}")


if __name__ == "__main__":
    cli.run(main)
