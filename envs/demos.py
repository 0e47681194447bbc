"""Demonstration datasets: an on-disk format written shard by shard and read lazily.

Layout of a dataset directory:
    meta.json              format version, camera/control settings, task list, episode index
    shard_00000/<field>.npy one uncompressed array per field, steps of many episodes
    shard_00001/...
Per-step fields (N = steps in the shard):
    image [N, H, W, 3] uint8     camera views before the action (meta "views", tiled along W)
    proprio [N, 8] float32       ee position, ee quaternion, jaw opening
    action [N, 7] float32        the expert's action (the label), in [-1, 1]
    ee_vel, ee_ang_vel, ee_acc [N, 3] float32, gripper_vel [N] float32   kinematics
Per-episode data lives in meta.json's "episodes" list: task name, task index (into the
"tasks" list), instruction, split key episode number, shard, start row, length, success.
Expert datasets store successful episodes only; DAgger datasets (meta "policy" names the
checkpoint that drove) store every episode, the expert's labels on the policy's states.

Writes go to a temporary sibling directory that is renamed into place only after
meta.json is complete, so an interrupted collection never leaves a dataset that looks
complete, and an existing dataset is replaced only on request and only at the very end.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
STEP_FIELDS = ("image", "proprio", "action", "ee_vel", "ee_ang_vel", "ee_acc", "gripper_vel")


class DatasetWriter:
    """Accumulates episodes into shards under a temporary directory; `finalize` publishes."""

    def __init__(self, path: str | os.PathLike, meta: dict, overwrite: bool = False):
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"dataset {self.path} already exists; pass overwrite to replace it")
        self.tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        self.tmp.mkdir(parents=True)
        self.meta = dict(meta, format_version=FORMAT_VERSION, fields=list(STEP_FIELDS), episodes=[])
        self.n_shards = 0

    def add_shard(self, steps: dict[str, np.ndarray], episodes: list[dict]) -> None:
        """steps: per-step arrays of the shard; episodes: their records (start, length, ...)."""
        d = self.tmp / f"shard_{self.n_shards:05d}"
        d.mkdir()
        for f in STEP_FIELDS:
            np.save(d / f"{f}.npy", np.ascontiguousarray(steps[f]))
        for e in episodes:
            self.meta["episodes"].append(dict(e, shard=self.n_shards))
        self.n_shards += 1

    def finalize(self) -> Path:
        self.meta.update(n_shards=self.n_shards, n_episodes=len(self.meta["episodes"]),
                         n_steps=int(sum(e["length"] for e in self.meta["episodes"])), created=time.time())
        with open(self.tmp / "meta.json", "w") as f:
            json.dump(self.meta, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        old = None
        if self.path.exists():
            old = self.path.with_name(f".{self.path.name}.old-{os.getpid()}")
            os.rename(self.path, old)
        os.rename(self.tmp, self.path)
        if old is not None:
            shutil.rmtree(old)
        return self.path

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


class DemoDataset:
    """Lazy reader: arrays are memory-mapped; `episode(i)` returns one episode's steps."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        meta_file = self.path / "meta.json"
        if not meta_file.exists():
            raise FileNotFoundError(f"{self.path} is not a complete dataset (no meta.json)")
        with open(meta_file) as f:
            self.meta = json.load(f)
        if self.meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"{self.path}: dataset format {self.meta.get('format_version')}, expected {FORMAT_VERSION}")
        self.episodes = self.meta["episodes"]
        self._shards: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.episodes)

    def shard(self, i: int) -> dict[str, np.ndarray]:
        if i not in self._shards:
            d = self.path / f"shard_{i:05d}"
            self._shards[i] = {f: np.load(d / f"{f}.npy", mmap_mode="r") for f in self.meta["fields"]}
        return self._shards[i]

    def episode(self, i: int) -> dict[str, np.ndarray]:
        e = self.episodes[i]
        s = self.shard(e["shard"])
        return {f: np.asarray(s[f][e["start"]: e["start"] + e["length"]]) for f in self.meta["fields"]}
