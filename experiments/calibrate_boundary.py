"""Calibrates HeiSD's kinematic boundary: how well retrieval drafts and drafter trees do as a
function of the fused kinematic metric, on demonstration episodes the datastore left out.

  python -m experiments.calibrate_boundary --demos=data/demos --datastore=checkpoints/datastore

For every held-out demo step (the datastore's meta.json lists them), the target decodes the
step's observation twice with the same settings as `--method=heisd`: once verifying the
retrieved candidates (then drafter rounds for what they leave), once with drafter SD alone,
and records target passes per action (TPA) and the retrieval draft's accepted length.
Binned by the metric (quantiles), this is the paper's "complementary advantages" analysis.
The boundary: tau_on = the lowest metric bin edge from which retrieval needs more target
passes than the drafter, tau_off = --hysteresis * tau_on; verify-skip's distance threshold
skip_eps = the largest nearest-key distance under which at least --skip_precision of the
retrieval drafts were accepted whole. Written to <datastore>/boundary.json (atomically; an
existing file is replaced only with --overwrite) with the per-bin table, and a plot.
"""

from __future__ import annotations

import os
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from envs import demos, tasks as tasks_lib
from heisd_jax import checkpoint, data, hybrid, kinematics, methods, results_io, retrieval, vla, vla_policy
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_string("demos", "data/demos", "The demonstrations the datastore was built from.")
cli.existing_dir("demos", "demonstrations dataset")
flags.DEFINE_string("datastore", str(vla_policy.DEFAULT_DATASTORE), "Datastore (experiments.build_datastore).")
cli.existing_dir("datastore", "datastore")
flags.DEFINE_string("checkpoint", str(vla_policy.DEFAULT_CHECKPOINT), "Target VLA checkpoint.")
cli.existing_dir("checkpoint", "policy checkpoint")
flags.DEFINE_string("drafter", str(vla_policy.DEFAULT_DRAFTER), "Drafter checkpoint.")
cli.existing_dir("drafter", "drafter checkpoint")
flags.DEFINE_string("settings", "", "heisd settings as key=value,key=value (as in experiments.sweep).")
flags.DEFINE_integer("max_steps", 20000, "At most this many held-out steps.")
flags.DEFINE_integer("batch", 512, "Steps decoded at once.")
flags.DEFINE_integer("bins", 10, "Metric bins (quantiles).")
flags.DEFINE_float("hysteresis", 0.7, "tau_off = hysteresis * tau_on.")
flags.DEFINE_float("skip_precision", 0.9, "Verify-skip: whole-acceptance rate required below skip_eps.")
flags.DEFINE_string("plot", "", "PNG of acceptance vs metric (default: <datastore>/boundary.png).")
flags.DEFINE_bool("overwrite", False, "Replace an existing boundary.json.")


def _held_out_steps(path: str, ds: demos.DemoDataset, episodes: list[int], key_spec, limit: int) -> dict:
    """Observations, action histories, tasks and kinematic features of the held-out steps
    (whole episodes in order, cut at `limit` steps)."""
    names = [t.name for t in tasks_lib.ALL_TASKS]
    chosen, n = [], 0
    for i in episodes:
        if n >= limit:
            break
        chosen.append(i)
        n += ds.episodes[i]["length"]
    table = data.load_steps(path, chosen)
    prev = np.concatenate([retrieval.episode_history(np.asarray(ds.episode(i)["action"], np.float32),
                                                     key_spec.history) for i in chosen])
    task = np.concatenate([np.full(ds.episodes[i]["length"], names.index(ds.episodes[i]["task"]), np.int32)
                           for i in chosen])
    cols = dict(image=table.image, proprio=table.proprio, instruction=table.instruction, prev=prev, task=task,
                feat=retrieval.demo_features(path, chosen))
    return {k: v[:limit] for k, v in cols.items()}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    out = Path(FLAGS.datastore) / methods.BOUNDARY_FILE
    if out.exists() and not FLAGS.overwrite:
        raise app.UsageError(f"{out} exists; pass --overwrite to replace it")
    if not 0 < FLAGS.hysteresis < 1 or not 0 < FLAGS.skip_precision <= 1 or FLAGS.bins < 2:
        raise app.UsageError("need 0 < --hysteresis < 1, 0 < --skip_precision <= 1 and --bins >= 2")
    settings = dict(kv.split("=", 1) for kv in FLAGS.settings.split(",") if kv)
    try:
        settings = methods.check_settings("heisd", settings)
        params, cfg, tok, _ = checkpoint.load_policy(FLAGS.checkpoint)
        dparams, _ = checkpoint.load_drafter(FLAGS.drafter, cfg, params)
        store, key_spec, meta = retrieval.load(FLAGS.datastore, tok, checkpoint.fingerprint(params))
        ds = demos.DemoDataset(FLAGS.demos)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    held = meta.get("holdout_episodes") or []
    if not held:
        raise app.UsageError(f"{FLAGS.datastore} holds out no demo episodes: rebuild it with --holdout > 0")
    cal = methods.load_calibration(FLAGS.datastore, meta)
    hcfg = methods.hybrid_config("heisd", settings, cal)
    hcfg.check_fits(cfg)
    steps = _held_out_steps(FLAGS.demos, ds, held, key_spec, FLAGS.max_steps)
    metric = np.asarray(kinematics.fused_metric(jnp.asarray(steps["feat"]), hcfg.metric))
    p = {"target": params, "drafter": dparams, "store": store}
    b = FLAGS.batch

    @jax.jit
    def measure(p, image, instruction, proprio, prev, task):
        obs = vla.Observation(image=image, instruction=instruction, proprio=proprio)
        cand, dist, valid = retrieval.query(p["store"], retrieval.make_keys(key_spec, tok, prev, proprio), task,
                                            hcfg.n_candidates, hcfg.max_dist)
        no = jnp.zeros(task.shape, bool)
        _, r = hybrid.decode(p, cfg, hcfg, obs, cand, valid, ~no, no)
        _, d = hybrid.decode(p, cfg, hcfg, obs, cand, valid, no, no)
        return r["target_passes"], r["retrieval_accepted"], d["target_passes"], dist[:, 0]

    n = len(metric)
    cols = {k: [] for k in ("tpa_retrieval", "accepted", "tpa_drafter", "dist")}
    for s in range(0, n, b):
        idx = np.arange(s, s + b) % n  # pad the last batch by wrapping (static shape)
        r = jax.device_get(measure(p, *(jnp.asarray(steps[k][idx]) for k in
                                        ("image", "instruction", "proprio", "prev", "task"))))
        keep = min(b, n - s)
        for k, v in zip(cols, r):
            cols[k].append(np.asarray(v)[:keep])
    cols = {k: np.concatenate(v) for k, v in cols.items()}
    edges = np.unique(np.quantile(metric, np.linspace(0, 1, FLAGS.bins + 1)))
    which = np.clip(np.searchsorted(edges, metric, side="right") - 1, 0, len(edges) - 2)
    table = []
    for j in range(len(edges) - 1):
        m = which == j
        if not m.any():
            continue
        table.append({"metric_lo": float(edges[j]), "metric_hi": float(edges[j + 1]), "steps": int(m.sum()),
                      "tpa_retrieval": float(cols["tpa_retrieval"][m].mean()),
                      "tpa_drafter": float(cols["tpa_drafter"][m].mean()),
                      "retrieval_accepted": float(cols["accepted"][m].mean()),
                      "retrieval_whole": float((cols["accepted"][m] == 7).mean())})
    loses = [row for row in table if row["tpa_retrieval"] > row["tpa_drafter"]]
    tau_on = loses[0]["metric_lo"] if loses else float(edges[-1])
    tau_on = max(tau_on, float(edges[1]))  # at least the lowest bin goes to retrieval
    tau_off = FLAGS.hysteresis * tau_on
    order = np.argsort(cols["dist"])
    whole_sorted = (cols["accepted"][order] == 7).astype(np.float64)
    precision = np.cumsum(whole_sorted) / np.arange(1, n + 1)
    ok = np.flatnonzero((precision >= FLAGS.skip_precision) & (np.arange(1, n + 1) >= 20))
    skip_eps = float(cols["dist"][order][ok[-1]]) if len(ok) else 0.0
    result = {"tau_on": float(tau_on), "tau_off": float(tau_off), "min_dwell": hcfg.boundary.min_dwell,
              "skip_eps": skip_eps, "table": table, "steps": n, "held_out_episodes": len(held),
              "settings": settings, "metric_scales": list(hcfg.metric.scales),
              "overall": {"tpa_retrieval": float(cols["tpa_retrieval"].mean()),
                          "tpa_drafter": float(cols["tpa_drafter"].mean()),
                          "retrieval_whole": float((cols["accepted"] == 7).mean())}}
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
    ax.set_xlabel("fused kinematic metric M")
    ax.set_ylabel("tokens per target pass")
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


if __name__ == "__main__":
    cli.run(main)
