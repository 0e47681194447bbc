"""The profiler runs a few closed-loop steps of the HeiSD method (shipped checkpoints) and
reports every part, the breakdown and the speedup over AR; bad flags fail before compiling."""

import gzip
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(argv):
    return subprocess.run([sys.executable, "-m", "experiments.profile", *argv], capture_output=True, text=True,
                          cwd=ROOT, timeout=1200)


@pytest.mark.slow  # the entry point in its own process, compiling every part of the method
def test_profiler_times_every_part_and_writes_a_trace(tmp_path):
    out = _run(["--method=heisd", "--settings=budget=fixed,top_k=4,depth=2,total_tokens=8", "--suites=goal", "--batch=2",
                "--steps=4", f"--trace_dir={tmp_path / 'trace'}", f"--hlo_dir={tmp_path / 'hlo'}",
                f"--out={tmp_path / 'p.json'}"])
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads((tmp_path / "p.json").read_text())
    assert "experiments.profile" in r["command"] and r["device"] and r["date"]  # the file says how it was made
    for part in ("act", "ar", "prefill", "prefill+cand", "retrieval", "draft_round", "verify_round", "env_step"):
        assert r["median_ms"][part] > 0, part
    # The speedup is AR's median over the method's (a ratio of this run's own figures); the
    # breakdown splits the method's decode step without remainder.
    assert r["speedup_vs_ar"] == pytest.approx(r["median_ms"]["ar"] / r["median_ms"]["act"])
    assert sum(r["breakdown_ms"].values()) == pytest.approx(r["median_ms"]["act"])
    m = r["median_ms"]  # a host loop's rate: one decode and one env step per control step
    assert r["control_steps_per_s"]["act"] == pytest.approx(1e3 / (m["act"] + m["env_step"]))
    assert 0 < r["per_action"]["target_passes"] <= 8
    for part in ("act", "ar", "env_step"):  # each traced on its own and summarised per kernel, per call
        assert any((tmp_path / "trace" / part).rglob("*.xplane.pb")), part
        lines = r["kernels"][part]
        assert lines and all(s["total_ms"] > 0 and s["top"] for s in lines.values()), part
        assert set(r["device_gaps"][part]) == set(lines), part  # the idle stretches of the same timelines
        assert set(r["host_control"][part]) == {"conditionals", "syncs", "graph_launches", "graph_launch_ms",
                                                "graph_update_ms"}, part
        with gzip.open(tmp_path / "hlo" / f"{part}.hlo.txt.gz", "rt") as f:  # where the kernels' names are
            assert "HloModule" in f.read(), part
    assert "act vs AR at batch 2" in out.stdout


def test_profiler_rejects_bad_settings_before_compiling():
    out = _run(["--method=heisd", "--settings=top_k=4,depth=2,total_tokens=99"])
    assert out.returncode != 0 and "total_tokens must be in 1..top_k*depth=8" in out.stderr
    out = _run(["--method=beam"])
    assert out.returncode != 0 and "heisd" in out.stderr
