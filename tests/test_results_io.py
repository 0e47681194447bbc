"""Result files: atomic writes, resumable loads, refusal of foreign or corrupt files, and
the provenance each records."""

import re
import subprocess
from pathlib import Path

import pytest

from heisd_jax import results_io


def test_round_trip_and_resume(tmp_path):
    path = tmp_path / "r.json"
    settings = {"method": "expert", "tasks": ["a"], "episodes_per_task": 2}
    assert results_io.load_resumable(path, settings) == {}
    episodes = {"a": [{"success": True, "steps": 3, "failure": None}, None]}
    results_io.write_json_atomic(path, {"settings": settings, "episodes": episodes})
    assert results_io.load_resumable(path, settings) == episodes
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temporary left behind


def test_gz_path_is_written_gzipped_and_read_back(tmp_path):
    path = tmp_path / "r.json.gz"
    settings = {"method": "ar", "tasks": ["a"]}
    episodes = {"a": [{"success": False, "steps": 7, "failure": "timeout"}]}
    results_io.write_json_atomic(path, {"settings": settings, "episodes": episodes})
    assert path.read_bytes()[:2] == b"\x1f\x8b"  # what its name says, so gzip-aware readers open it
    assert results_io.load_resumable(path, settings) == episodes
    plain = tmp_path / "plain.json.gz"  # named .gz but plain (as written before): still read
    plain.write_text('{"x": 1}')
    assert results_io.read_json(plain) == {"x": 1}
    with pytest.raises(ValueError, match="not a readable JSON file"):
        results_io.read_json(tmp_path / "missing.json")


def test_foreign_settings_are_refused_and_file_kept(tmp_path):
    path = tmp_path / "r.json"
    results_io.write_json_atomic(path, {"settings": {"method": "expert"}, "episodes": {}})
    before = path.read_text()
    with pytest.raises(ValueError, match="other settings"):
        results_io.load_resumable(path, {"method": "ar"})
    assert path.read_text() == before


def test_the_same_files_read_from_another_folder_resume_the_run(tmp_path):
    """A run is its files' contents, not their paths: a job that copies the tree elsewhere
    resumes it; another file at the same path, or a path with nothing there, does not."""
    path = tmp_path / "r.json"

    def settings(folder, digest):
        return {"method": "ar", "checkpoint": f"/{folder}/checkpoints/vla", "contents": {"checkpoint": digest}}
    episodes = {"a": [None]}
    results_io.write_json_atomic(path, {"settings": settings("one", "deddfac7"), "episodes": episodes})
    assert results_io.load_resumable(path, settings("two", "deddfac7")) == episodes
    for other in (settings("one", "0123abcd"), settings("two", None)):
        with pytest.raises(ValueError, match="other settings"):
            results_io.load_resumable(path, other)
    results_io.write_json_atomic(path, {"settings": settings("one", None), "episodes": episodes})
    assert results_io.load_resumable(path, settings("one", None)) == episodes
    with pytest.raises(ValueError, match="other settings"):
        results_io.load_resumable(path, settings("two", None))


def test_corrupt_file_is_refused(tmp_path):
    path = tmp_path / "r.json"
    path.write_text('{"settings": {"method": "exp')
    with pytest.raises(ValueError, match="not a readable results file"):
        results_io.load_resumable(path, {"method": "expert"})


def test_provenance_names_command_commit_device_and_date():
    rec = results_io.provenance("python -m experiments.x --a=1")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1]).stdout.strip() or None
    assert rec["command"] == "python -m experiments.x --a=1" and rec["commit"] == head
    assert rec["device"] and re.fullmatch(r"\d{4}-\d{2}-\d{2}", rec["date"])


def test_provenance_takes_the_commit_from_the_environment(monkeypatch):
    """A tree copied to another machine with a stale .git records the commit it was given."""
    monkeypatch.setenv("HEISD_COMMIT", "abc1234")
    assert results_io.provenance("x")["commit"] == "abc1234"
