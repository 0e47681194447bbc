"""The sweep entry point (resume after an interruption) and the report."""

import json
import subprocess
import sys
from pathlib import Path

from experiments import report
from heisd_jax import results_io

ROOT = Path(__file__).resolve().parents[1]


def _sweep(out, *extra):
    argv = [sys.executable, "-m", "experiments.sweep", "--methods=expert", "--suites=spatial,object",
            "--tasks=left_block_plate,pick_red_block", "--episodes=1", "--num_envs=2", f"--out={out}", *extra]
    p = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=1500)
    assert p.returncode == 0, p.stderr[-3000:]
    return p.stdout


def test_sweep_resumes_after_an_interruption_without_loss_or_duplicates(tmp_path):
    out = tmp_path / "sweep.jsonl"
    _sweep(out)
    sweep, recs = results_io.read_sweep(out)
    assert sorted(r["cell"]["suite"] for r in recs) == ["object", "spatial"]
    assert all(r["suite"]["episodes"] == 1 and r["git_commit"] is not None and "jax" in r["versions"] for r in recs)
    lines = out.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[:-1]) + lines[-1][: len(lines[-1]) // 2])  # crash mid-write of the last cell
    stdout = _sweep(out)
    assert "partial last line" in stdout and "1 to run" in stdout
    _, again = results_io.read_sweep(out)
    assert sorted(results_io.cell_key(r["cell"]) for r in again) == sorted(results_io.cell_key(r["cell"]) for r in recs)
    bad = subprocess.run([sys.executable, "-m", "experiments.sweep", "--methods=expert,nope", f"--out={out}"],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert bad.returncode != 0 and "valid methods" in bad.stderr


def _record(method, settings, suite, sr, ms, al=None):
    decode = {"tokens_per_target_pass": al, "target_passes_per_action": 7 / al} if al else {}
    return {"cell": {"method": method, "settings": settings, "suite": suite, "seed": 0, "num_envs": 8, "episodes": 2},
            "suite": {"episodes": 20, "successes": int(sr * 20), "success_rate": sr, **decode},
            "timing": {"ms_per_control_step": ms}, "episode_acceptance_length": [al] * 3 if al else []}


def test_report_measures_speedup_against_ar_of_the_same_sweep(tmp_path):
    recs = [_record("ar", {}, "goal", 0.5, 20.0, 1.0), _record("drafter", {"relax_bins": 9}, "goal", 0.45, 16.0, 1.8),
            _record("drafter", {"relax_bins": 9}, "long", 0.2, 10.0, 1.7)]
    rows = {(r["method"], r["suite"]): r for r in report.summarize(recs)}
    d = rows[("drafter:relax_bins=9", "goal")]
    assert abs(d["speedup_vs_ar"] - 1.25) < 1e-9 and abs(d["sr_drop_vs_ar"] - 0.05) < 1e-9
    assert rows[("drafter:relax_bins=9", "long")]["speedup_vs_ar"] is None  # no AR cell for long: no ratio
    text = report.table(list(rows.values()))
    assert "drafter:relax_bins=9" in text and "1.25" in text
    pngs = report.plots(list(rows.values()), tmp_path / "plots")
    assert all(p.stat().st_size > 1000 for p in pngs)
