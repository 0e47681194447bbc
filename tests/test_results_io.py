"""Result files: atomic writes, resumable loads, refusal of foreign or corrupt files."""

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


def test_foreign_settings_are_refused_and_file_kept(tmp_path):
    path = tmp_path / "r.json"
    results_io.write_json_atomic(path, {"settings": {"method": "expert"}, "episodes": {}})
    before = path.read_text()
    with pytest.raises(ValueError, match="other settings"):
        results_io.load_resumable(path, {"method": "ar"})
    assert path.read_text() == before


def test_corrupt_file_is_refused(tmp_path):
    path = tmp_path / "r.json"
    path.write_text('{"settings": {"method": "exp')
    with pytest.raises(ValueError, match="not a readable results file"):
        results_io.load_resumable(path, {"method": "expert"})
