"""The whole target build from nothing, on CPU at toy sizes (one task, a few episodes, a tiny
model, a few steps), with the fresh round after its evaluation: every stage runs as its own
command and records itself; a rerun of the same command finds every stage done and runs none,
also once the datasets and earlier policies are gone (a build moved to another machine with
what a poll brings back)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow  # four compiles of rendered rollouts: ~10 minutes on 2 cores


def test_build_from_nothing_smoke_run_and_resume(tmp_path):
    work = tmp_path / "build"
    cmd = [sys.executable, "-m", "experiments.build_target", f"--work={work}", "--suites=spatial",
           "--tasks=left_block_plate", "--demo_episodes=2", "--rounds=1", "--dagger_episodes=2", "--steps=20",
           "--dagger_steps=8", "--batch_size=8", "--d_model=32", "--n_layers=1", "--num_envs=2", "--eval_episodes=2",
           "--image_size=16", "--skip=drafter,datastore,calibration", "--fresh_round"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=2400)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    stages = json.loads((work / "build.json").read_text())["stages"]
    assert list(stages) == ["demos", "train0", "dagger1", "train1", "eval", "fresh_demos", "dagger2", "train2",
                            "fresh_eval"]
    assert all(s["seconds"] > 0 for s in stages.values())
    assert "compile" in stages["demos"]["time"] and "policy_success" in stages["dagger1"]
    # a training stage splits its seconds too, the imports through the export
    assert all(part in stages["train0"]["time"] for part in ("start", "load", "first step", "steps", "export"))
    assert len(json.loads(stages["train1"]["held_out_decisive"])) == 7
    # The fresh round trains on the aggregate, its own two datasets drawn 4x as often.
    log = (work / "logs" / "train2.log").read_text()
    assert all(f"{work / d}: " in log for d in ("demos", "dagger1", "fresh_demos", "dagger2")) and "% of the draws" in log
    assert (work / "vla2" / "0").is_dir() and (work / "eval_ar.json").exists() and (work / "eval_ar_fresh.json").exists()
    for gone in ("demos", "dagger1", "fresh_demos", "dagger2", "vla0", "vla1", "run0", "run1", "run2"):
        shutil.rmtree(work / gone)
    before = (work / "build.json").read_text()
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, (again.stdout + again.stderr)[-4000:]
    assert (work / "build.json").read_text() == before  # every stage was done: none ran again
