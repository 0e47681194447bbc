"""Calibrates HeiSD's kinematic boundary: how well retrieval drafts and drafter trees do as a
function of the fused kinematic metric, on demonstration episodes the datastore left out.

  python -m experiments.calibrate_boundary --demos=data/demos --datastore=checkpoints/datastore

For every held-out demo step (the datastore's meta.json lists them), the target decodes the
step's observation twice with the same settings as `--method=heisd`: once verifying the
retrieved candidates (then drafter rounds for what they leave), once with drafter SD alone.
The measurement and the rule that turns it into tau_on, tau_off and skip_eps are
`heisd_jax.harness.offline.boundary` (its module doc states the rule); this script loads the
inputs, prints the per-bin table and writes <datastore>/boundary.json (atomically; an
existing file is replaced only with --overwrite) and a plot.
"""

from __future__ import annotations

import os
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import numpy as np

from envs import demos, tasks as tasks_lib
from heisd_jax import results_io
from heisd_jax.harness import data, methods
from heisd_jax.harness.offline import boundary, datastore
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_string("demos", "data/demos", "The demonstrations the datastore was built from.")
cli.existing_dir("demos", "demonstrations dataset")
cli.define_paths("datastore", "checkpoint", "drafter")
flags.DEFINE_string("settings", "", "heisd settings as key=value,key=value (as in experiments.sweep).")
flags.DEFINE_integer("max_steps", 20000, "At most this many held-out steps.")
flags.DEFINE_integer("batch", 512, "Steps decoded at once.")
flags.DEFINE_integer("bins", boundary.BoundaryRule.bins, "Metric bins (quantiles).")
flags.DEFINE_float("hysteresis", boundary.BoundaryRule.hysteresis, "tau_off = hysteresis * tau_on.")
flags.DEFINE_float("skip_precision", boundary.BoundaryRule.skip_precision,
                   "Verify-skip: whole-acceptance rate required below skip_eps.")
flags.DEFINE_string("plot", "", "PNG of acceptance vs metric (default: <datastore>/boundary.png).")
flags.DEFINE_bool("overwrite", False, "Replace an existing boundary.json.")


def _held_out_steps(path: str, ds: demos.DemoDataset, episodes: list[int], key_spec, limit: int,
                    executed=None) -> dict:
    """Observations, action histories, tasks and kinematic features of the held-out steps
    (whole episodes in order, cut at `limit` steps). `executed(episodes)`: the actions
    executed on those episodes' steps where they are not the recorded ones (a datastore of
    the target's own rollouts, `build_datastore --values=rollout`)."""
    names = [t.name for t in tasks_lib.ALL_TASKS]
    chosen, n = [], 0
    for i in episodes:
        if n >= limit:
            break
        chosen.append(i)
        n += ds.episodes[i]["length"]
    table = data.load_steps(path, chosen)
    acts = [np.asarray(ds.episode(i)["action"], np.float32) for i in chosen]
    if executed is not None:
        acts = np.split(executed(chosen), np.cumsum([len(a) for a in acts])[:-1])
    prev = np.concatenate([datastore.episode_history(a, key_spec.history) for a in acts])
    task = np.concatenate([np.full(ds.episodes[i]["length"], names.index(ds.episodes[i]["task"]), np.int32)
                           for i in chosen])
    cols = dict(image=table.image, proprio=table.proprio, instruction=table.instruction, prev=prev, task=task,
                feat=datastore.demo_features(path, chosen))
    return {k: v[:limit] for k, v in cols.items()}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    out = Path(FLAGS.datastore) / methods.BOUNDARY_FILE
    if out.exists() and not FLAGS.overwrite:
        raise app.UsageError(f"{out} exists; pass --overwrite to replace it")
    try:
        rule = boundary.BoundaryRule(bins=FLAGS.bins, hysteresis=FLAGS.hysteresis, skip_precision=FLAGS.skip_precision)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    settings = dict(kv.split("=", 1) for kv in FLAGS.settings.split(",") if kv)
    try:
        settings = methods.check_settings("heisd", settings)
        stack, cfg, tok, hcfg, key_spec, meta = methods.load_hybrid(
            "heisd", cli.paths("checkpoint", "drafter", "datastore"), settings)
        ds = demos.DemoDataset(FLAGS.demos)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    held = meta.get("holdout_episodes") or []
    if not held:
        raise app.UsageError(f"{FLAGS.datastore} holds out no demo episodes: rebuild it with --holdout > 0")
    executed = None if meta.get("values") != "rollout" else \
        (lambda episodes: datastore.executed_actions(stack["target"], cfg, tok, FLAGS.demos, episodes))
    steps = _held_out_steps(FLAGS.demos, ds, held, key_spec, FLAGS.max_steps, executed)
    measured = boundary.measure(stack, cfg, hcfg, key_spec, tok, steps, FLAGS.batch)
    result = boundary.calibrate(measured, rule, hcfg.boundary.min_dwell,
                                about={"held_out_episodes": len(held), "settings": settings,
                                       "metric_scales": list(hcfg.metric.scales)})
    table, tau_on, tau_off, skip_eps = result["table"], result["tau_on"], result["tau_off"], result["skip_eps"]
    results_io.write_json_atomic(out, result)
    print(f"{'metric bin':>18}{'steps':>7}{'TPA retr':>10}{'TPA draft':>10}{'retr acc':>10}{'whole':>8}")
    for row in table:
        print(f"{row['metric_lo']:8.2f}-{row['metric_hi']:<9.2f}{row['steps']:>7}{row['tpa_retrieval']:>10.2f}"
              f"{row['tpa_drafter']:>10.2f}{row['retrieval_accepted']:>10.2f}{row['retrieval_whole']:>8.2f}")
    print(f"tau_on {tau_on:.3f}, tau_off {tau_off:.3f}, skip_eps {skip_eps:.4f} -> {out}")
    _plot(table, tau_on, tau_off, FLAGS.plot or str(Path(FLAGS.datastore) / "boundary.png"))


def _plot(table, tau_on, tau_off, path):
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    mid = [(r["metric_lo"] + r["metric_hi"]) / 2 for r in table]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(mid, [7 / r["tpa_retrieval"] for r in table], "o-", label="retrieval drafts (then drafter)")
    ax.plot(mid, [7 / r["tpa_drafter"] for r in table], "s-", label="drafter trees")
    ax.axvline(tau_on, ls="--", c="gray", label="tau_on / tau_off")
    ax.axvline(tau_off, ls=":", c="gray")
    ax.set_xscale("symlog", linthresh=0.1)
    ax.set_xlim(left=0)  # the metric is >= 0
    ax.set_xlabel("fused kinematic metric M")
    ax.set_ylabel("tokens per target pass")
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


if __name__ == "__main__":
    cli.run(main)
