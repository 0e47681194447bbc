"""Sweep result files: resume without loss or duplicates, repair of a crash's partial line."""

import json

import pytest

from heisd_jax import results_io

SWEEP = {"episodes": 2, "tasks": None}


def _rec(method, suite, sr=0.5):
    return {"cell": {"method": method, "settings": {}, "suite": suite, "seed": 0, "num_envs": 2},
            "summary": {"success_rate": sr}}


def test_resume_keeps_every_cell_once(tmp_path):
    p = tmp_path / "s.jsonl"
    f = results_io.SweepFile(p, SWEEP)
    f.append(_rec("ar", "goal"))
    f.append(_rec("ar", "long"))
    g = results_io.SweepFile(p, SWEEP)  # "restart"
    assert len(g.records) == 2 and results_io.cell_key(_rec("ar", "goal")["cell"]) in g.done()
    with pytest.raises(ValueError, match="already recorded"):
        g.append(_rec("ar", "goal"))
    g.append(_rec("drafter", "goal"))
    settings, recs = results_io.read_sweep(p)
    assert settings == SWEEP and [r["cell"]["method"] for r in recs] == ["ar", "ar", "drafter"]


def test_a_sweep_without_a_finished_cell_leaves_no_file(tmp_path):
    p = tmp_path / "new" / "s.jsonl"
    f = results_io.SweepFile(p, SWEEP)  # opened (a refused or interrupted sweep stops here)
    assert not p.exists() and f.done() == set()
    f.append(_rec("ar", "goal"))
    settings, recs = results_io.read_sweep(p)
    assert settings == SWEEP and [r["cell"]["suite"] for r in recs] == ["goal"]
    with pytest.raises(ValueError, match="is a folder, not a results file"):
        results_io.SweepFile(tmp_path / "new", SWEEP)  # a folder


def test_partial_trailing_line_is_cut_and_redone(tmp_path):
    p = tmp_path / "s.jsonl"
    f = results_io.SweepFile(p, SWEEP)
    f.append(_rec("ar", "goal"))
    with open(p, "a") as fh:  # a crash in the middle of writing the next record
        fh.write(json.dumps(_rec("ar", "long"))[:25])
    g = results_io.SweepFile(p, SWEEP)
    assert g.repaired and len(g.records) == 1
    g.append(_rec("ar", "long"))
    assert [r["cell"]["suite"] for r in results_io.read_sweep(p)[1]] == ["goal", "long"]


def test_damage_before_the_end_and_foreign_sweeps_are_refused(tmp_path):
    p = tmp_path / "s.jsonl"
    f = results_io.SweepFile(p, SWEEP)
    f.append(_rec("ar", "goal"))
    f.append(_rec("ar", "long"))
    lines = p.read_text().split("\n")
    lines[1] = lines[1][:10]
    bad = tmp_path / "bad.jsonl"
    bad.write_text("\n".join(lines))
    before = bad.read_text()
    with pytest.raises(ValueError, match="line 2 is damaged"):
        results_io.SweepFile(bad, SWEEP)
    assert bad.read_text() == before  # untouched
    before = p.read_text()
    with pytest.raises(ValueError, match="other settings"):
        results_io.SweepFile(p, {"episodes": 50, "tasks": None})
    assert p.read_text() == before  # refused, never overwritten
    other = tmp_path / "other.json"
    other.write_text('{"settings": {}}\n')
    with pytest.raises(ValueError, match="not a heisd-jax-sweep-v1"):
        results_io.SweepFile(other, SWEEP)
    assert other.read_text() == '{"settings": {}}\n'
