"""Batched evaluation sweeps: methods x suites x seeds x batch sizes, one JSON line per cell.

  python -m experiments.sweep --methods=ar,drafter:acceptance=token_relaxed,relax_bins=9 \
      --suites=all --episodes=50 --num_envs=256 --out=results/sweep.jsonl
  python -m experiments.sweep --config=sweep.json       # the same settings as a JSON object
  python -m experiments.report results/sweep.jsonl

A method is NAME or NAME:key=value,key=value (e.g. drafter:top_k=4,depth=2,total_tokens=8,
heisd:skip=false); `heisd_jax.harness.methods.check_settings` lists each method's valid keys.
Every cell runs the batched evaluator on the suite's tasks and is appended to --out (with
the method's full settings, the git commit, the device and library versions) as soon as it
finishes: rerunning the same command skips finished cells, and a partial last line left by
a crash is cut off and its cell redone. A file from a sweep of other fixed settings
(episodes, tasks, checkpoints, --physics) is refused, never overwritten. Seeds change only the keys
handed to the policy: the initial states are the fixed evaluation ones. One env holds every
task of the sweep and task ids and seeds are data, so the suites and seeds of one method,
settings and batch size run one compiled program, traced and compiled once per sweep
(`Programs`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import time
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import mujoco
from envs import tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import results_io, sharding
from heisd_jax.harness import evaluator as ev, methods
from experiments import cli

FLAGS = flags.FLAGS
cli.define_cost_flags()
flags.DEFINE_string("config", "", "JSON file with any of: methods, suites, tasks, episodes, num_envs, seeds.")
flags.DEFINE_string("methods", "ar", "Comma-separated methods, each NAME or NAME:key=value,key=value.")
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names.")
flags.DEFINE_integer("episodes", 50, "Evaluation initial states per task.")
flags.DEFINE_list("num_envs", ["0"], "Batch sizes (parallel envs); 0: heisd_jax.harness.evaluator.default_num_envs() (512 per "
                  "GPU, 64 on a CPU).")
flags.DEFINE_list("seeds", ["0"], "Policy seeds.")
cli.define_tail_flag()
cli.define_store_flag()
cli.define_physics_flag()
cli.define_paths("checkpoint", "drafter", "datastore")
flags.DEFINE_string("out", "results/sweep.jsonl", "Results file (JSON lines).")


def parse_methods(spec: str) -> list[tuple[str, dict]]:
    try:
        return methods.parse_method_list(spec)
    except ValueError as e:
        raise app.UsageError(str(e)) from e


def _provenance() -> dict:
    import flax  # noqa: PLC0415

    return {"git_commit": results_io.commit(short=False), "device": jax.devices()[0].device_kind,
            "n_devices": jax.device_count(),
            "versions": {"jax": jax.__version__, "flax": flax.__version__, "mujoco": mujoco.__version__}}


class Programs:
    """One env over every task of the sweep and, per method, settings and batch size, one
    policy and its compiled rollouts: task ids and seeds are data, so the suites and seeds of
    a method share one program, compiled once and not traced again (and, across runs, loaded
    from the executable store)."""

    def __init__(self, task_list):
        self.task_list, self.envs, self.built = tuple(task_list), {}, {}

    def get(self, cell: dict):
        name, settings = cell["method"], dict(cell["settings"])
        key = (name, json.dumps(settings, sort_keys=True), cell["num_envs"])
        if key not in self.built:
            env_cfg = dataclasses.replace(methods.env_config(name, FLAGS.checkpoint), physics=cli.physics_config())
            if env_cfg not in self.envs:
                self.envs[env_cfg] = TabletopEnv(self.task_list, env_cfg)
            env = self.envs[env_cfg]
            policy = methods.make_policy(name, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                         datastore=FLAGS.datastore, batch_size=cell["num_envs"] // jax.device_count(),
                                         **cli.cost_kwargs(), **settings)
            self.built[key] = (env, policy, {}, cli.executable_store(name, settings))
        return self.built[key]


def run_cell(cell: dict, task_list, programs: Programs, progress) -> dict:
    env, policy, rollouts, store = programs.get(cell)
    timing = {"batch_seconds": 0.0, "control_steps": 0, "env_steps": 0, "compile_seconds": 0.0,
              "tail_envs": FLAGS.tail_envs}

    def on_batch(results, t):
        for k in ("batch_seconds", "control_steps", "env_steps"):
            timing[k] += t[k]
        timing["compile_seconds"] = t["compile_seconds"]
        progress(results, t["episodes"])

    t0 = time.perf_counter()
    cfg = ev.EvalConfig(episodes_per_task=cell["episodes"], num_envs=cell["num_envs"], tail_envs=FLAGS.tail_envs)
    results = ev.evaluate(env, policy, cfg, on_batch=on_batch, seed=cell["seed"], tasks={t.name for t in task_list},
                          rollouts=rollouts, store=store)
    summary = ev.summarize(env.tasks, results)
    timing["ms_per_control_step"] = 1e3 * timing["batch_seconds"] / max(timing["control_steps"], 1)
    timing["wall_seconds"] = time.perf_counter() - t0
    per_episode_al = [r["decode"]["tokens"] / max(r["decode"]["target_passes"], 1e-9)
                      for recs in results.values() for r in recs if r and "tokens" in r.get("decode", {})]
    return {"cell": cell, "numerics": methods.numerics_ran(policy), "suite": summary["suites"].get(cell["suite"], {}),
            "tasks": summary["tasks"],
            "timing": timing, "episode_acceptance_length": per_episode_al, **_provenance(),
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S")}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    conf = {}
    if FLAGS.config:
        try:
            conf = json.loads(Path(FLAGS.config).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise app.UsageError(f"--config={FLAGS.config}: {e}") from e
        unknown = set(conf) - {"methods", "suites", "tasks", "episodes", "num_envs", "seeds"}
        if unknown:
            raise app.UsageError(f"--config: unknown keys {sorted(unknown)}; valid: methods, suites, tasks, episodes, "
                                 f"num_envs, seeds")
    method_spec = conf.get("methods", FLAGS.methods)
    method_list = parse_methods(";".join(method_spec) if isinstance(method_spec, list) else method_spec)
    suites_arg = conf.get("suites", FLAGS.suites)
    suites = list(tasks_lib.SUITES) if suites_arg == "all" else (
        suites_arg if isinstance(suites_arg, list) else suites_arg.split(","))
    task_filter = conf.get("tasks", FLAGS.tasks) or None
    episodes = int(conf.get("episodes", FLAGS.episodes))
    num_envs = [int(x) or ev.default_num_envs() for x in conf.get("num_envs", FLAGS.num_envs)]
    seeds = [int(x) for x in conf.get("seeds", FLAGS.seeds)]
    try:
        chosen = tasks_lib.get_tasks(",".join(suites), task_filter)
        per_suite = {s: tuple(t for t in chosen if t.suite == s) for s in suites}
        ev.EvalConfig(episodes_per_task=episodes, num_envs=min(num_envs), tail_envs=FLAGS.tail_envs)
        mesh = sharding.env_mesh()
        for b in filter(None, num_envs + [FLAGS.tail_envs]):  # before any cell runs, not mid-sweep
            sharding.check_batch(b, mesh)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    per_suite = {s: t for s, t in per_suite.items() if t}
    sweep = {"episodes": episodes, "tasks": task_filter, "checkpoint": os.path.abspath(FLAGS.checkpoint),
             "drafter": os.path.abspath(FLAGS.drafter), "datastore": os.path.abspath(FLAGS.datastore),
             "physics": dataclasses.asdict(cli.physics_config()),
             "contents": cli.contents(sorted({n for m, _ in method_list for n in methods.get(m).loads}))}
    try:
        store = results_io.SweepFile(FLAGS.out, sweep)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if store.repaired:
        print(f"{FLAGS.out}: cut off a partial last line (interrupted write); that cell is redone")
    cells = [dict(method=m, settings=s, config=cli.config_digest(m, s), suite=su, seed=sd, num_envs=b,
                  episodes=episodes) for (m, s), su, sd, b in itertools.product(method_list, per_suite, seeds, num_envs)]
    done = store.done()
    todo = [c for c in cells if results_io.cell_key(c) not in done]
    for m, s in method_list:  # a method that does not fit, or lacks a cost table, is refused now, not at its cell
        rows = sorted({c["num_envs"] // jax.device_count() for c in todo if (c["method"], c["settings"]) == (m, s)})
        if rows:
            cli.check_methods([(m, s)], rows, FLAGS.checkpoint, FLAGS.datastore)
    n_eps = {su: len(t) * episodes for su, t in per_suite.items()}
    total = sum(n_eps[c["suite"]] for c in todo)
    print(f"sweep: {len(cells)} cells, {len(cells) - len(todo)} already in {FLAGS.out}, {len(todo)} to run "
          f"({total} episodes)")
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn  # noqa: PLC0415

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} episodes"),
                  TextColumn("success so far {task.fields[sr]}"), TimeElapsedColumn(), TimeRemainingColumn()) as bar:
        task = bar.add_task("sweep", total=total, sr="-")
        programs = Programs(t for ts in per_suite.values() for t in ts)
        counts = {"succ": 0, "n": 0}
        for cell in todo:
            bar.update(task, description=f"{cell['method']} {cell['suite']} B={cell['num_envs']} seed={cell['seed']}")

            def progress(results, n, cell=cell):
                bar.advance(task, n)

            rec = run_cell(cell, per_suite[cell["suite"]], programs, progress)
            counts["succ"] += rec["suite"].get("successes", 0)
            counts["n"] += rec["suite"].get("episodes", 0)
            bar.update(task, sr=f"{counts['succ'] / max(counts['n'], 1):.3f}")
            store.append(rec)
    print(f"results: {os.path.abspath(FLAGS.out)}  (python -m experiments.report {FLAGS.out})")


if __name__ == "__main__":
    cli.run(main)
