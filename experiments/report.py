"""Summary of a sweep: per method and suite, success rate, acceptance length, target passes
per action, wall-clock per control step and the speedup over AR *measured in the same
sweep* (same suite, seed and batch size); optional plots.

  python -m experiments.report results/sweep.jsonl --plots=results/plots
"""

from __future__ import annotations

import collections
import json
from pathlib import Path

from absl import app, flags

from heisd_jax import results_io
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_string("plots", "", "Directory for PNG plots (needs matplotlib: pip install -e '.[plots]').")


def method_label(cell: dict) -> str:
    return cli.method_label(cell["method"], dict(sorted(cell["settings"].items())))


def labels(records: list[dict]) -> list[str]:
    """Each record's method label; where one label covers cells run under different method
    configs (the same settings given, another default: a sweep file resumed across a release
    that changed one), each is told apart by its config digest ('unrecorded' before sweeps
    recorded it)."""
    names = [method_label(r["cell"]) for r in records]
    configs = collections.defaultdict(set)
    for name, r in zip(names, records):
        configs[name].add(r["cell"].get("config"))
    return [name + (f" @config {r['cell'].get('config') or 'unrecorded'}" if len(configs[name]) > 1 else "")
            for name, r in zip(names, records)]


def summarize(records: list[dict]) -> list[dict]:
    """One row per cell, with speedup and success-rate drop against the AR cell of the same
    suite, seed and batch size (None where the sweep has no such AR cell)."""
    ar = {(r["cell"]["suite"], r["cell"]["seed"], r["cell"]["num_envs"]): r for r in records
          if r["cell"]["method"] == "ar" and not r["cell"]["settings"]}
    rows = []
    for r, name in zip(records, labels(records)):
        c, s, t = r["cell"], r["suite"], r["timing"]
        base = ar.get((c["suite"], c["seed"], c["num_envs"]))
        rows.append({
            "method": name, "suite": c["suite"], "seed": c["seed"], "num_envs": c["num_envs"],
            "episodes": s.get("episodes", 0), "success_rate": s.get("success_rate"),
            "acceptance_length": s.get("tokens_per_target_pass"), "target_passes_per_action": s.get("target_passes_per_action"),
            "ms_per_control_step": t["ms_per_control_step"],
            "speedup_vs_ar": base["timing"]["ms_per_control_step"] / t["ms_per_control_step"] if base else None,
            "sr_drop_vs_ar": (base["suite"]["success_rate"] - s["success_rate"]) if base else None,
            "episode_acceptance_length": r.get("episode_acceptance_length", []), "device": r.get("device")})
    return rows


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


def table(rows: list[dict]) -> str:
    head = f"{'method':<44}{'suite':<9}{'B':>6}{'seed':>5}{'eps':>6}{'SR':>7}{'AL':>6}{'TPA':>6}{'ms/step':>9}{'x AR':>7}"
    lines = [head, "-" * len(head)]
    for r in sorted(rows, key=lambda r: (r["suite"], r["num_envs"], r["seed"], r["method"])):
        lines.append(f"{r['method'][:43]:<44}{r['suite']:<9}{r['num_envs']:>6}{r['seed']:>5}{r['episodes']:>6}"
                     f"{_fmt(r['success_rate'], '.3f'):>7}{_fmt(r['acceptance_length'], '.2f'):>6}"
                     f"{_fmt(r['target_passes_per_action'], '.2f'):>6}{r['ms_per_control_step']:>9.1f}"
                     f"{_fmt(r['speedup_vs_ar'], '.2f'):>7}")
    return "\n".join(lines)


def plots(rows: list[dict], out: Path) -> list[Path]:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    out.mkdir(parents=True, exist_ok=True)
    written = []
    fig, ax = plt.subplots(figsize=(6, 4))
    by_method = collections.defaultdict(list)
    for r in rows:
        if r["speedup_vs_ar"] is not None and r["method"] != "ar":
            by_method[r["method"]].append(r)
    for m, rs in sorted(by_method.items()):
        ax.scatter([100 * r["sr_drop_vs_ar"] for r in rs], [r["speedup_vs_ar"] for r in rs], label=m)
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xlabel("success-rate drop vs AR (points)")
    ax.set_ylabel("speedup vs AR (same sweep)")
    if by_method:
        ax.legend(fontsize=7)
    fig.tight_layout()
    written.append(out / "speedup_vs_sr_drop.png")
    fig.savefig(written[-1], dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    for m in sorted({r["method"] for r in rows}):
        vals = [v for r in rows if r["method"] == m for v in r["episode_acceptance_length"]]
        if vals:
            ax.hist(vals, bins=30, alpha=0.5, label=m)
    ax.set_xlabel("acceptance length per episode (tokens per target pass)")
    ax.set_ylabel("episodes")
    ax.legend(fontsize=7)
    fig.tight_layout()
    written.append(out / "acceptance_length_hist.png")
    fig.savefig(written[-1], dpi=120)
    plt.close(fig)
    return written


def main(argv):
    if len(argv) != 2:
        raise app.UsageError("usage: python -m experiments.report RESULTS.jsonl [--plots=DIR]")
    try:
        sweep, records = results_io.read_sweep(argv[1])
    except (OSError, ValueError) as e:
        raise app.UsageError(str(e)) from e
    rows = summarize(records)
    print(f"sweep {json.dumps(sweep)}: {len(records)} cells")
    print(table(rows))
    if FLAGS.plots:
        for p in plots(rows, Path(FLAGS.plots)):
            print(f"plot: {p}")


if __name__ == "__main__":
    cli.run(main)
