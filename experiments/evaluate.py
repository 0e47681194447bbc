"""Closed-loop batched evaluation on the fixed evaluation initial states.

  python -m experiments.evaluate --method=ar --suites=all --episodes=50 --num_envs=64 \
      --out=results/eval_ar.json

Writes per-task and per-suite success rates and per-action decoding statistics (target
passes per action, wall-clock per batched control step) to --out (JSON) after every batch;
rerunning the same command resumes where it stopped. A results file written with other
settings is refused, never overwritten (use another --out).
"""

from __future__ import annotations

import os
import time

T_START = time.perf_counter()  # the summary's wall time counts the imports below (JAX, MuJoCo)

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flag before JAX starts)
from envs import tasks as tasks_lib
from envs.env import TabletopEnv
import jax

from heisd_jax import budget, cost_model, evaluate as ev, hybrid, methods, results_io, sharding, spec_decode, vla_policy
from experiments import cli

FLAGS = flags.FLAGS
cli.define_calibrate_costs()
flags.DEFINE_enum("method", "expert", sorted(methods.METHODS), "Decoding method (policy) to evaluate.")
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names (default: every task of the suites).")
flags.DEFINE_integer("episodes", 50, "Evaluation initial states per task (the first N of the fixed 50).")
flags.DEFINE_integer("num_envs", 64, "Episodes run in parallel.")
flags.DEFINE_string("out", "results/eval.json", "Results file (JSON); resumed if it exists with the same settings.")
flags.DEFINE_string("checkpoint", str(vla_policy.DEFAULT_CHECKPOINT), "Policy checkpoint of the VLA methods.")
cli.existing_dir("checkpoint", "policy checkpoint")
flags.DEFINE_string("drafter", str(vla_policy.DEFAULT_DRAFTER), "Speculative methods: the drafter checkpoint.")
cli.existing_dir("drafter", "drafter checkpoint")
flags.DEFINE_string("datastore", str(vla_policy.DEFAULT_DATASTORE), "retrieval/heisd: the retrieval datastore.")
cli.existing_dir("datastore", "datastore")
flags.DEFINE_enum("acceptance", None, list(spec_decode.ACCEPTANCE),
                  "Drafter trees: acceptance rule (default: strict for drafter, token_relaxed for retrieval/heisd).")
flags.DEFINE_integer("relax_bins", None, "token_relaxed: accept a draft within this many bins of the target's choice.")
flags.DEFINE_integer("top_k", None, "Draft tree: children kept per level (EAGLE-2 top-k; default 8).")
flags.DEFINE_integer("depth", None, "Draft tree: depth (default 4).")
flags.DEFINE_integer("total_tokens", None, "Draft tree: nodes verified per round (<= top_k * depth; default 32).")
flags.DEFINE_enum("mode", None, list(hybrid.MODES), "heisd: hybrid (kinematic boundary) or one mode at every step.")
flags.DEFINE_enum("retrieval_acceptance", None, list(hybrid.RETRIEVAL_ACCEPTANCE),
                  "retrieval/heisd: acceptance rule for retrieval drafts (heisd default seq_relaxed).")
flags.DEFINE_integer("retrieval_relax_bins", None, "token_relaxed retrieval acceptance: bins (default 9).")
flags.DEFINE_integer("n_candidates", None, "retrieval/heisd: retrieved actions verified per step (default 4; 0: no "
                     "datastore query, the recent actions alone, verify-skip off).")
flags.DEFINE_integer("recent_candidates", None, "retrieval/heisd: the env's own last executed actions verified as "
                     "further candidates each retrieval step (default: heisd 4, retrieval 0; our design).")
flags.DEFINE_enum("verify", None, list(hybrid.VERIFY), "Retrieval drafts verified inside the prefill or in a second pass.")
flags.DEFINE_enum("continuation", None, list(hybrid.CONTINUATION),
                  "retrieval/heisd with budget=fixed: what decodes the rest of an action after the prefill and its "
                  "accepted candidate prefix: drafter rounds (default) or single-token AR passes (no drafter).")
flags.DEFINE_bool("skip", None, "heisd: verify-skip (default on; off with strict acceptance).")
flags.DEFINE_integer("k_skip", None, "Verify-skip: at most this many consecutive skipped target passes.")
flags.DEFINE_float("tau_on", None, "Boundary: metric above which the drafter mode starts (default: the calibration).")
flags.DEFINE_float("tau_off", None, "Boundary: metric below which the retrieval mode starts.")
flags.DEFINE_enum("budget", None, list(budget.BUDGETS),
                  "retrieval/heisd: draft budget chosen per step from measured costs (auto; heisd default) or the "
                  "one fixed tree (fixed).")
flags.DEFINE_string("budget_trees", None, "budget=auto: draft trees to choose from besides AR, TOPKxDEPTHxTOTAL "
                    "separated by '/' (default: the --top_k/--depth/--total_tokens tree if given, else 4x2x8/8x4x32).")
flags.DEFINE_float("budget_forget", None, "budget=auto: per unchosen step, share by which an option's estimate "
                   "returns to its long-run mean (default 0.05; 0 = never).")
flags.DEFINE_float("budget_margin", None, "budget=auto: a drafting option must be predicted this much faster than "
                   "AR to be chosen (default 0.1).")
flags.DEFINE_enum("dtype", None, list(methods.DTYPES), "VLA methods: parameters and KV cache in this dtype (default float32).")
flags.DEFINE_string("cost_cache", str(cost_model.DEFAULT_CACHE),
                    "budget=auto: directory of measured cost tables (per device, model and batch size); '' = none.")

METHOD_FLAGS = ("acceptance", "relax_bins", "top_k", "depth", "total_tokens", "mode", "retrieval_acceptance",
                "retrieval_relax_bins", "n_candidates", "recent_candidates", "verify", "continuation", "skip", "k_skip",
                "tau_on", "tau_off", "budget", "budget_trees", "budget_forget", "budget_margin", "dtype")


def method_settings() -> dict:
    """The method's own settings from the flags that were given (validated: a clear error
    before anything loads or compiles)."""
    given = {k: getattr(FLAGS, k) for k in METHOD_FLAGS if getattr(FLAGS, k) is not None}
    if FLAGS.method == "expert" or (FLAGS.method == "ar" and set(given) - {"dtype"}):
        if given:
            raise app.UsageError(f"--method={FLAGS.method} takes none of --{', --'.join(given)}")
        return {}
    try:
        return methods.check_settings(FLAGS.method, given)
    except ValueError as e:
        raise app.UsageError(str(e)) from e


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        task_list = tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
        cfg = ev.EvalConfig(episodes_per_task=FLAGS.episodes, num_envs=FLAGS.num_envs)
        sharding.check_batch(cfg.num_envs, sharding.env_mesh())
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    settings = {"method": FLAGS.method, "tasks": [t.name for t in task_list], "episodes_per_task": cfg.episodes_per_task}
    if FLAGS.method != "expert":
        settings["checkpoint"] = os.path.abspath(FLAGS.checkpoint)
    kwargs = method_settings()
    settings.update(kwargs)
    paths = {"drafter": FLAGS.drafter, "datastore": FLAGS.datastore}
    for key in methods.CHECKPOINTS.get(FLAGS.method, ()):
        if key != "checkpoint_path":
            name = key.removesuffix("_path")
            settings[name] = os.path.abspath(paths[name])
    try:
        done = results_io.load_resumable(FLAGS.out, settings)
        env = TabletopEnv(task_list, methods.env_config(FLAGS.method, FLAGS.checkpoint))
        policy = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                     datastore=FLAGS.datastore, batch_size=cfg.num_envs // jax.device_count(),
                                     cost_cache=FLAGS.cost_cache or None,
                                     calibrate_costs=FLAGS.calibrate_costs, **kwargs)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    n_total = len(task_list) * cfg.episodes_per_task
    n_todo = len(ev.pending_episodes(env, cfg, done))
    print(f"{FLAGS.method}: {len(task_list)} tasks x {cfg.episodes_per_task} episodes, {n_todo} to run, {cfg.num_envs} envs in parallel")
    t_start = time.perf_counter()
    progress = {"episodes": n_total - n_todo}
    # Wall-clock of this invocation's batches (a resumed run times only what it ran). Its wall
    # time splits into compile (the rollout's, tracing included), run (the batches: device
    # work and fetching results) and host (the rest: imports, loading, setup, writing results).
    timing = {"device": str(jax.devices()[0].device_kind), "num_envs": cfg.num_envs, "batches": 0,
              "batch_seconds": 0.0, "control_steps": 0, "env_steps": 0, "compile_seconds": 0.0}

    table = policy.meta.get("cost_table")
    if table is not None:
        print(table.report())
        timing["cost_table"] = {"options": table.options, "fixed_ms": table.fixed_ms, "round_ms": table.round_ms,
                                "ceiling_ar_over_prefill": table.ceiling}

    def write(results):
        summary = ev.summarize(env.tasks, results)
        if timing["control_steps"]:
            timing["ms_per_control_step"] = 1e3 * timing["batch_seconds"] / timing["control_steps"]
            timing["env_steps_per_s"] = timing["env_steps"] / timing["batch_seconds"]
        timing["wall_seconds"] = time.perf_counter() - T_START
        timing["run_seconds"] = timing["batch_seconds"]
        timing["host_seconds"] = timing["wall_seconds"] - timing["compile_seconds"] - timing["run_seconds"]
        results_io.write_json_atomic(FLAGS.out, {"settings": settings, "episodes": results, "summary": summary,
                                                 "timing": timing})
        return summary

    def on_batch(results, t):
        progress["episodes"] += t["episodes"]
        timing["batches"] += 1
        timing["compile_seconds"] = t["compile_seconds"]
        timing["devices"] = t.get("devices", 1)
        for k in ("batch_seconds", "control_steps", "env_steps"):
            timing[k] += t[k]
        summary = write(results)
        succ = sum(s["successes"] for s in summary["suites"].values())
        print(f"  {progress['episodes']}/{n_total} episodes, success so far {succ / max(progress['episodes'], 1):.3f}, "
              f"batch {t['batch_seconds']:.1f}s ({1e3 * t['batch_seconds'] / max(t['control_steps'], 1):.1f} ms per "
              f"control step, {t['env_steps'] / t['batch_seconds']:.0f} env steps/s), "
              f"elapsed {time.perf_counter() - t_start:.0f}s", flush=True)

    results = ev.evaluate(env, policy, cfg, done, on_batch)
    summary = write(results)
    print(f"\n{'suite':<10}{'episodes':>10}{'success':>10}{'passes/act':>12}{'accept len':>12}")
    for name, s in summary["suites"].items():
        passes, al = s.get("target_passes_per_action"), s.get("tokens_per_target_pass")
        print(f"{name:<10}{s['episodes']:>10}{s['success_rate']:>10.3f}{'-' if passes is None else f'{passes:.2f}':>12}"
              f"{'-' if al is None else f'{al:.2f}':>12}")
    if timing["control_steps"]:
        print(f"{timing['ms_per_control_step']:.1f} ms per control step ({cfg.num_envs} envs: decode + physics"
              f"{' + camera' if env.config.render else ''}), compile {timing['compile_seconds']:.0f}s")
    print(f"time: {timing['wall_seconds']:.0f}s wall = compile {timing['compile_seconds']:.0f}s + run "
          f"{timing['run_seconds']:.0f}s + host {timing['host_seconds']:.0f}s")
    print(f"results: {os.path.abspath(FLAGS.out)}")


if __name__ == "__main__":
    cli.run(main)
