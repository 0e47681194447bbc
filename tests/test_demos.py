"""Demonstration datasets: format round trip, atomic publication, and collection end to end."""

import json
import os

import numpy as np
import pytest
from absl import flags
from absl.testing import flagsaver

from envs import demos


def _steps(n, h=8):
    rng = np.random.default_rng(n)
    return {
        "image": rng.integers(0, 255, (n, h, h, 3), dtype=np.uint8),
        "proprio": rng.normal(size=(n, 8)).astype(np.float32),
        "action": rng.uniform(-1, 1, (n, 7)).astype(np.float32),
        "ee_vel": rng.normal(size=(n, 3)).astype(np.float32),
        "ee_ang_vel": rng.normal(size=(n, 3)).astype(np.float32),
        "ee_acc": rng.normal(size=(n, 3)).astype(np.float32),
        "gripper_vel": rng.normal(size=(n,)).astype(np.float32),
    }


def test_write_read_round_trip(tmp_path):
    path = tmp_path / "ds"
    w = demos.DatasetWriter(path, {"note": "test"})
    a, b = _steps(5), _steps(7)
    w.add_shard({k: np.concatenate([a[k], b[k]]) for k in a},
                [dict(task="x", start=0, length=5), dict(task="y", start=5, length=7)])
    assert not path.exists()  # nothing visible before finalize
    w.finalize()
    ds = demos.DemoDataset(path)
    assert len(ds) == 2 and ds.meta["n_steps"] == 12 and ds.meta["note"] == "test"
    for i, ref in enumerate((a, b)):
        ep = ds.episode(i)
        for k in demos.STEP_FIELDS:
            np.testing.assert_array_equal(ep[k], ref[k])


def test_interrupted_write_leaves_no_dataset(tmp_path):
    path = tmp_path / "ds"
    w = demos.DatasetWriter(path, {})
    w.add_shard(_steps(3), [dict(task="x", start=0, length=3)])
    w.abort()
    assert not path.exists() and os.listdir(tmp_path) == []
    with pytest.raises(FileNotFoundError, match="not a complete dataset"):
        demos.DemoDataset(path)


def test_existing_dataset_is_kept_unless_overwrite(tmp_path):
    path = tmp_path / "ds"
    w = demos.DatasetWriter(path, {"v": 1})
    w.add_shard(_steps(2), [dict(task="x", start=0, length=2)])
    w.finalize()
    with pytest.raises(FileExistsError):
        demos.DatasetWriter(path, {"v": 2})
    w2 = demos.DatasetWriter(path, {"v": 2}, overwrite=True)
    assert demos.DemoDataset(path).meta["v"] == 1  # still the old one until finalize
    w2.add_shard(_steps(4), [dict(task="x", start=0, length=4)])
    w2.finalize()
    assert demos.DemoDataset(path).meta["v"] == 2
    assert sorted(os.listdir(tmp_path)) == ["ds"]


@pytest.mark.slow  # compiles and runs the expert's rendered rollout: ~100 s on 2 cores
def test_collect_demos_end_to_end(tmp_path):
    from experiments import collect_demos

    out = tmp_path / "demos"
    flags.FLAGS.mark_as_parsed()
    with flagsaver.flagsaver(suites="goal", tasks=["lift_blue_cylinder"], episodes_per_task=1, suite_weights=["goal:2"],
                             num_envs=2,
                             image_size=16, out=str(out), action_noise=0.05):
        collect_demos.main([])
    ds = demos.DemoDataset(out)
    assert ds.meta["n_episodes"] == 2 and ds.meta["split"] == "train"  # 1 per task x 2 for the goal suite
    ep = ds.episode(0)
    n = ds.episodes[0]["length"]
    assert ep["image"].shape == (n, 16, 32, 3) and ep["action"].shape == (n, 7)  # agent view | wrist view
    assert ds.meta["views"] == ["agentview", "wrist"]
    assert np.all(np.abs(ep["action"]) <= 1.0)
    assert ep["action"][-1, 6] == 1.0  # holding the cylinder up: jaw closed
    with open(out / "meta.json") as f:
        assert json.load(f)["tasks"][0]["instruction"] == "pick up the blue cylinder and hold it up"
