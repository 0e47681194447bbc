"""The sweep entry point (resume after an interruption) and the report."""

import json
import re
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from experiments import report
from heisd_jax import results_io
from heisd_jax.harness import methods

ROOT = Path(__file__).resolve().parents[1]


def _sweep(out, *extra):
    argv = [sys.executable, "-m", "experiments.sweep", "--methods=expert", "--suites=spatial,object",
            "--tasks=left_block_plate,pick_red_block", "--episodes=1", "--num_envs=2", f"--out={out}", *extra]
    p = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=1500)
    assert p.returncode == 0, p.stderr[-3000:]
    return p.stdout


@pytest.mark.slow  # the entry point, three times in its own process
def test_sweep_resumes_after_an_interruption_without_loss_or_duplicates(tmp_path):
    out = tmp_path / "sweep.jsonl"
    _sweep(out)
    sweep, recs = results_io.read_sweep(out)
    assert sorted(r["cell"]["suite"] for r in recs) == ["object", "spatial"]
    for r in recs:  # provenance: this checkout's commit (a hash, not None), the library versions
        assert r["suite"]["episodes"] == 1 and re.fullmatch(r"[0-9a-f]{40}", r["git_commit"] or "")
        assert set(r["versions"]) == {"jax", "flax", "mujoco"} and r["versions"]["jax"] == jax.__version__
    lines = out.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[:-1]) + lines[-1][: len(lines[-1]) // 2])  # crash mid-write of the last cell
    stdout = _sweep(out)
    assert "partial last line" in stdout and "1 to run" in stdout
    _, again = results_io.read_sweep(out)
    assert sorted(results_io.cell_key(r["cell"]) for r in again) == sorted(results_io.cell_key(r["cell"]) for r in recs)
    bad = subprocess.run([sys.executable, "-m", "experiments.sweep", "--methods=expert,nope", f"--out={out}"],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert bad.returncode != 0 and "valid methods" in bad.stderr


def test_method_list_is_parsed_and_every_setting_checked_before_anything_runs():
    assert methods.parse_method_list("ar,drafter:acceptance=token_relaxed,relax_bins=9;heisd:skip=false") == [
        ("ar", {}), ("drafter", {"acceptance": "token_relaxed", "relax_bins": 9}), ("heisd", {"skip": False})]
    for spec, reason in [("expert,nope", "unknown method 'nope'; valid methods: ar, drafter, expert, heisd, retrieval"),
                         ("drafter:top_k", "'top_k' of 'drafter' is not key=value"),
                         ("ar:top_k=4", r"unknown settings \['top_k'\]; valid: dtype"),
                         ("drafter:top_k=4,depth=2,total_tokens=99", r"total_tokens must be in 1..top_k\*depth=8"),
                         ("drafter:relax_bins=9", "relax_bins is only used with acceptance='token_relaxed'"),
                         ("heisd:skip=maybe", "not a boolean")]:
        with pytest.raises(ValueError, match=reason):
            methods.parse_method_list(spec)


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
    # One label over two method configs (a sweep resumed across a changed default): told apart.
    old, new = _record("heisd", {}, "goal", 0.4, 9.0, 2.0), _record("heisd", {}, "goal", 0.5, 10.0, 1.9)
    new["cell"]["config"] = "0123456789abcdef"
    assert [r["method"] for r in report.summarize([old, new])] == ["heisd @config unrecorded",
                                                                    "heisd @config 0123456789abcdef"]
    assert [r["method"] for r in report.summarize([new])] == ["heisd"]
    pngs = report.plots(list(rows.values()), tmp_path / "plots")
    assert sorted(p.name for p in pngs) == ["acceptance_length_hist.png", "speedup_vs_sr_drop.png"]
    assert all(p.read_bytes().startswith(b"\x89PNG") and p.stat().st_size > 1000 for p in pngs)
