"""Closed-loop batched evaluation on the fixed evaluation initial states.

  python -m experiments.evaluate --method=ar --suites=all --episodes=50 --out=results/eval_ar.json

Writes per-task and per-suite success rates and per-action decoding statistics (target
passes per action, wall-clock per batched control step) to --out (JSON) after every batch,
and every --save_every_s seconds within a refilled queue (the episodes that have ended);
rerunning the same command resumes where it stopped. SIGTERM or Ctrl-C stops a refilled
queue after its round in progress, the episodes that have ended written first (a second
signal stops at once). A results file written with other settings is refused, never
overwritten (use another --out).
"""

from __future__ import annotations

import dataclasses
import os
import time

T_START = time.perf_counter()  # the summary's wall time counts the imports below (JAX, MuJoCo)

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flag before JAX starts)
from envs import tasks as tasks_lib
from envs.env import TabletopEnv
import jax

from heisd_jax import results_io, sharding
from heisd_jax.harness import evaluator as ev, methods
from heisd_jax.timing import Phases, split_text
from experiments import cli, eval_report, method_flags

FLAGS = flags.FLAGS
cli.define_cost_flags()
flags.DEFINE_enum("method", "expert", sorted(methods.METHODS), "Decoding method (policy) to evaluate.")
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names (default: every task of the suites).")
flags.DEFINE_integer("episodes", 50, "Evaluation initial states per task (the first N of the fixed 50).")
flags.DEFINE_integer("num_envs", 0, "Episodes run in parallel; 0: heisd_jax.harness.evaluator.default_num_envs() (512 per GPU, "
                     "64 on a CPU).", lower_bound=0)
flags.DEFINE_bool("refill", True, "An env whose episode ends takes the next pending episode: every pending episode in "
                  "one call, results written at its end. --norefill: batches of --num_envs episodes, each waiting "
                  "for its slowest, results written after each batch.")
cli.define_tail_flag()
flags.DEFINE_float("save_every_s", ev.EvalConfig.save_every_s, "With refill: every this many seconds, the episodes "
                   "that have ended are written to --out, so an interrupted run (a lease that ends, say) resumes "
                   "after them; 0: results written only at the end of the queue.")
cli.define_store_flag()
flags.DEFINE_bool("compile_only", False, "Compile the rollout this command would run (filling the compilation cache "
                  "and the executable store, e.g. before a sweep), print where its compile time went, run nothing and "
                  "write no results.")
flags.DEFINE_bool("deterministic", False, "Compile the rollout with deterministic GPU reductions "
                  "(heisd_jax.xla_options.DETERMINISTIC): a rerun then plays the same episodes, where the physics' "
                  "scatter-add atomics can otherwise end a rare episode a step apart. Slower on a GPU.")
flags.DEFINE_string("out", "results/eval.json", "Results file (JSON); resumed if it exists with the same settings.")
cli.define_paths("checkpoint", "drafter", "datastore")
for _name in method_flags.define():  # --top_k, --budget, ...: every field of the VLA methods' settings
    flags.declare_key_flag(_name)
cli.define_physics_flag()


def main(argv):
    del argv
    host_phases = Phases(mark=T_START)  # the host's seconds before the batches, from the imports
    host_phases.lap("start")
    logging.set_verbosity(logging.WARNING)
    try:
        task_list = tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
        cfg = ev.EvalConfig(episodes_per_task=FLAGS.episodes, num_envs=FLAGS.num_envs or ev.default_num_envs(),
                            refill=FLAGS.refill, tail_envs=FLAGS.tail_envs, deterministic=FLAGS.deterministic,
                            save_every_s=FLAGS.save_every_s)
        for n in filter(None, (cfg.num_envs, cfg.tail_envs)):  # the tail's batch too, if any
            sharding.check_batch(n, sharding.env_mesh())
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    settings = {"method": FLAGS.method, "tasks": [t.name for t in task_list], "episodes_per_task": cfg.episodes_per_task}
    if FLAGS.method != "expert":
        settings["checkpoint"] = os.path.abspath(FLAGS.checkpoint)
    kwargs = method_flags.given(FLAGS.method)
    settings.update(kwargs)
    settings["config"] = cli.config_digest(FLAGS.method, kwargs)
    env_physics = cli.physics_config()
    settings["physics"] = dataclasses.asdict(env_physics)
    paths = {"drafter": FLAGS.drafter, "datastore": FLAGS.datastore}
    for name in methods.get(FLAGS.method).loads:
        if name != "checkpoint":
            settings[name] = os.path.abspath(paths[name])
    settings["contents"] = cli.contents(methods.get(FLAGS.method).loads)
    try:
        previous = results_io.read_resumable(FLAGS.out, settings)
        done = previous.get("episodes", {})
        earlier = results_io.earlier_runs(previous) if done else []  # the speeds of the runs it resumes
        env = TabletopEnv(task_list, dataclasses.replace(methods.env_config(FLAGS.method, FLAGS.checkpoint),
                                                         physics=env_physics))
        policy = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                     datastore=FLAGS.datastore, batch_size=cfg.num_envs // jax.device_count(),
                                     **cli.cost_kwargs(), **kwargs)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    store = cli.executable_store(FLAGS.method, kwargs)
    n_total = len(task_list) * cfg.episodes_per_task
    n_todo = len(ev.pending_episodes(env, cfg, done))
    if FLAGS.compile_only:
        split = ev.compile_rollout(env, policy, cfg, done, store=store)
        print(f"{FLAGS.method}: {n_todo} episodes pending, {cfg.num_envs} envs: " +
              (f"compiled in {eval_report.compile_text(split)}" if split else "nothing to compile"))
        print(split_text(time.perf_counter() - T_START, {}, label="wall"))
        return
    print(f"{FLAGS.method}: {len(task_list)} tasks x {cfg.episodes_per_task} episodes, {n_todo} to run, {cfg.num_envs} envs in parallel")
    # host = start (imports, flags, cache set-up) + setup (the env, the policy and what it
    # loads, the store's digests; the device's start-up) + other (inputs, results written)
    host_phases.lap("setup")
    t_start = host_phases.mark  # the batches start: `elapsed` counts from here
    progress = {"episodes": n_total - n_todo}
    # Wall-clock of this invocation's batches (a resumed run times only what it ran). Its wall
    # time splits into compile (the rollout's, tracing included), run (the batches: device
    # work and fetching results) and host (the rest: imports, loading, setup, writing results).
    timing = {"device": str(jax.devices()[0].device_kind), "num_envs": cfg.num_envs, "tail_envs": cfg.tail_envs,
              "batches": 0, "batch_seconds": 0.0, "control_steps": 0, "env_steps": 0, "compile_seconds": 0.0,
              **({"earlier": earlier} if earlier else {})}

    table = policy.meta.get("cost_table")
    if table is not None:
        print(table.report())
        timing["cost_table"] = {"options": table.options, "fixed_ms": table.fixed_ms, "round_ms": table.round_ms,
                                "ceiling_ar_over_prefill": table.ceiling}

    made = results_io.provenance(cli.command_line())
    # A budget=auto method built as plain AR at this batch size (methods._as_ar) says so.
    as_ar = {"runs_as_ar": True} if policy.meta.get("runs_as_ar") else {}

    def folded(t):  # `timing` with one call's timing (`on_batch`'s, or a running or stopped call's share) added
        out = {**timing, "batches": timing["batches"] + 1, "compile_seconds": t["compile_seconds"],
               "compile_split": t["compile_split"], "devices": t.get("devices", 1)}
        for k in ("batch_seconds", "control_steps", "env_steps"):
            out[k] = timing[k] + t[k]
        return out

    def write(results, timing):  # completes `timing` in place (speed, wall, host), writes the file, returns its data
        summary = ev.summarize(env.tasks, results)
        if timing["control_steps"]:
            timing["ms_per_control_step"] = 1e3 * timing["batch_seconds"] / timing["control_steps"]
            timing["env_steps_per_s"] = timing["env_steps"] / timing["batch_seconds"]
        timing["wall_seconds"] = time.perf_counter() - T_START
        timing["host_seconds"] = timing["wall_seconds"] - timing["compile_seconds"] - timing["batch_seconds"]
        timing["host_split"] = {**host_phases.seconds,
                                "other": timing["host_seconds"] - sum(host_phases.seconds.values())}
        if earlier:  # this run and the ones it resumed, summed
            timing["all_runs"] = results_io.all_runs([*earlier, timing])
        data = {"settings": settings, "numerics": methods.numerics_ran(policy), "episodes": results,
                "summary": summary, "timing": timing, **as_ar, **made}
        results_io.write_json_atomic(FLAGS.out, data)
        return data

    def on_batch(results, t):
        progress["episodes"] += t["episodes"]
        timing.update(folded(t))
        summary = write(results, timing)["summary"]
        succ = sum(s["successes"] for s in summary["suites"].values())
        print(f"  {progress['episodes']}/{n_total} episodes, success so far {succ / max(progress['episodes'], 1):.3f}, "
              f"batch {t['batch_seconds']:.1f}s ({1e3 * t['batch_seconds'] / max(t['control_steps'], 1):.1f} ms per "
              f"control step, {t['env_steps'] / t['batch_seconds']:.0f} env steps/s), "
              f"elapsed {time.perf_counter() - t_start:.0f}s", flush=True)

    def on_progress(results, t):  # the running call's share so far, marked as such
        summary = write(results, {**folded(t), "running": True})["summary"]
        ended = sum(s["episodes"] for s in summary["suites"].values())
        print(f"  {ended}/{n_total} episodes ended (saved), success so far "
              f"{sum(s['successes'] for s in summary['suites'].values()) / max(ended, 1):.3f}, "
              f"elapsed {time.perf_counter() - t_start:.0f}s", flush=True)

    stop = cli.StopOnSignals()
    try:
        results = ev.evaluate(env, policy, cfg, done, on_batch, store=store, on_progress=on_progress, stop=stop)
    except ev.EvaluationStopped as e:
        if e.timing is not None:  # the stopped call's speed, its ended episodes already written
            timing.update(folded(e.timing), stopped=True)
            write(e.results, timing)
            t = e.timing
            print(f"  stopped after {t['control_steps']} control steps: {1e3 * t['batch_seconds'] / max(t['control_steps'], 1):.1f} "
                  f"ms per control step, compile {t['compile_seconds']:.0f}s", flush=True)
        ended = sum(r is not None for recs in e.results.values() for r in recs)
        print(f"stopped: {ended}/{n_total} episodes in {os.path.abspath(FLAGS.out)}; the same command runs the rest",
              flush=True)
        stop.exit()
    print(eval_report.final_report(write(results, timing), camera=env.config.render, out=os.path.abspath(FLAGS.out)))


if __name__ == "__main__":
    cli.run(main)
