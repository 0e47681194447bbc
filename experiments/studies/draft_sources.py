"""Which draft source the target accepts where: retrieval drafts vs drafter trees on the
target's own closed-loop states, per phase of the task and per kinematic-metric bin (the
paper's "complementary advantages" analysis).

  python -m experiments.studies.draft_sources --suites=all --envs=256 --steps=200 --out=results/draft_sources.json

Runs the target (greedy AR) on the fixed evaluation initial states while the scripted expert
watches every step without acting and names the phase the state is in (approach, descend,
grasp, lift, ...). Every running step is then decoded twice with `--method=heisd`'s settings
(`heisd_jax.harness.offline.boundary.measure`, as the boundary calibration does on held-out demos):
verifying the retrieved candidates first (drafter rounds for what they leave), and with
drafter trees alone. The retrieval keys use the actions the target itself executed before
the step. Prints and records, per expert phase and per bin of the fused kinematic metric:
the share of steps, target passes per action (TPA) both ways, tokens per target pass (7 /
TPA), the retrieval draft's mean accepted length and the share of steps where it was
accepted whole; --plot draws tokens per target pass both ways, per phase and per metric bin.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import expert, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import results_io
from heisd_jax.harness import methods, vla_policy
from heisd_jax.harness.offline import boundary
from heisd_jax.tokenizer import ACTION_DIM
from experiments import cli

FLAGS = flags.FLAGS
cli.define_paths("checkpoint", "drafter", "datastore")
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names.")
flags.DEFINE_integer("envs", 256, "Envs recorded in parallel (cycling over the tasks and their evaluation states).")
flags.DEFINE_integer("steps", 200, "Control steps recorded per env (an episode that ends early stops counting).")
flags.DEFINE_string("settings", "", "heisd settings as key=value,key=value (as in experiments.sweep).")
flags.DEFINE_integer("batch", 512, "Steps decoded at once.")
flags.DEFINE_integer("bins", boundary.BoundaryRule.bins, "Kinematic-metric bins (quantiles).")
flags.DEFINE_string("out", "results/draft_sources.json", "Results JSON.")
flags.DEFINE_string("plot", "", "PNG of tokens per target pass by phase and by metric bin (optional).")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    for name in ("envs", "steps", "batch", "bins"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1, got {getattr(FLAGS, name)}")
    settings = dict(kv.split("=", 1) for kv in FLAGS.settings.split(",") if kv)
    try:
        task_list = tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
        env = TabletopEnv(task_list, methods.env_config("heisd", FLAGS.checkpoint))
        paths = cli.paths("checkpoint", "drafter", "datastore")
        stack, cfg, tok, hcfg, key_spec, _ = methods.load_hybrid("heisd", paths, settings, env)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    learner = vla_policy.decoding_policy("ar", stack["target"], cfg, tok, vla_policy.ar)

    n = FLAGS.envs
    tids, keys = env.cycling_eval_starts(n)
    t0 = time.perf_counter()
    run = jax.jit(lambda p, k, t: rollout.record_episodes(env, dataclasses.replace(learner, params=p), k, t,
                                                          FLAGS.steps, teacher=expert.observer(env), beta=0.0))
    final, traj = jax.device_get(run(learner.params, keys, jnp.asarray(tids, jnp.int32)))
    steps, phase = boundary.closed_loop_steps(traj, np.asarray(final.step), np.asarray(env.instructions)[tids],
                                              np.asarray(env.global_index)[tids], key_spec.history)
    print(f"recorded {n} envs x {FLAGS.steps} steps: {len(phase)} running steps in {time.perf_counter() - t0:.0f}s",
          flush=True)
    measured = boundary.measure(stack, cfg, hcfg, key_spec, tok, steps, FLAGS.batch)
    by_phase = boundary.group_table(measured, phase, expert.PHASE_NAMES)
    _, by_metric = boundary.metric_table(measured, FLAGS.bins)
    _print("phase", [r["group"] for r in by_phase], by_phase)
    _print("metric bin", [f"{r['metric_lo']:.2f}-{r['metric_hi']:.2f}" for r in by_metric], by_metric)
    record = {**results_io.provenance(cli.command_line()),
              "steps": len(phase), "by_phase": by_phase, "by_metric": by_metric,
              "overall": boundary.group_table(measured, np.zeros(len(phase), np.int32), ("all",))[0]}
    Path(FLAGS.out).parent.mkdir(parents=True, exist_ok=True)
    results_io.write_json_atomic(FLAGS.out, record)
    print(f"results: {os.path.abspath(FLAGS.out)}")
    if FLAGS.plot:
        _plot(by_phase, by_metric, FLAGS.plot)


def _print(what: str, labels: list[str], rows: list[dict]) -> None:
    print(f"\n{what:<14}{'steps':>7}{'share':>7}{'TPA retr':>10}{'TPA draft':>10}{'tok/pass retr':>14}"
          f"{'tok/pass draft':>15}{'retr acc':>9}{'whole':>7}")
    total = sum(r["steps"] for r in rows)
    for label, r in zip(labels, rows):
        print(f"{label:<14}{r['steps']:>7}{r['steps'] / total:>7.1%}{r['tpa_retrieval']:>10.2f}{r['tpa_drafter']:>10.2f}"
              f"{ACTION_DIM / r['tpa_retrieval']:>14.2f}{ACTION_DIM / r['tpa_drafter']:>15.2f}"
              f"{r['retrieval_accepted']:>9.2f}{r['retrieval_whole']:>7.1%}")


def _plot(by_phase: list[dict], by_metric: list[dict], path: str) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    x = np.arange(len(by_phase))
    a.bar(x - 0.2, [ACTION_DIM / r["tpa_retrieval"] for r in by_phase], 0.4, label="retrieval drafts (then drafter)")
    a.bar(x + 0.2, [ACTION_DIM / r["tpa_drafter"] for r in by_phase], 0.4, label="drafter trees")
    a.set_xticks(x, [f"{r['group']}\n{r['share']:.0%}\nwhole {r['retrieval_whole']:.0%}" for r in by_phase],
                 fontsize=7, rotation=30)
    a.set_ylabel("tokens per target pass")
    a.set_title("by expert phase (share of steps; retrieval accepted whole)", fontsize=9)
    a.legend(fontsize=8)
    mid = [(r["metric_lo"] + r["metric_hi"]) / 2 for r in by_metric]
    b.plot(mid, [ACTION_DIM / r["tpa_retrieval"] for r in by_metric], "o-", label="retrieval drafts (then drafter)")
    b.plot(mid, [ACTION_DIM / r["tpa_drafter"] for r in by_metric], "s-", label="drafter trees")
    b.set_xscale("symlog", linthresh=0.1)
    b.set_xlim(left=0)  # the metric is >= 0
    whole = b.twinx()
    whole.plot(mid, [r["retrieval_whole"] for r in by_metric], ":", c="gray")
    whole.set_ylim(0, 1)
    whole.set_ylabel("retrieval accepted whole (share, dotted)", fontsize=8)
    b.set_xlabel("fused kinematic metric M (quantile bins)")
    b.set_title("by kinematic metric", fontsize=9)
    b.legend(fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


if __name__ == "__main__":
    cli.run(main)
