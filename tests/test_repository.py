"""The repository stays small enough to travel: a leased GPU machine (experiments/gpu_job.sh,
docs/reproduce.md) gets a copy of the working tree, at most 64 MiB with the mujoco wheels in
`.whl/` (about 9.3 MiB), so the tracked files keep under 52 MiB. Results are committed small
(large evaluation JSONs as .json.gz, which experiments.compare_evals reads)."""

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIMIT_MIB = 52


def _tracked_sizes() -> dict[str, int]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    paths = [p for p in names.decode().split("\0") if p]
    return {p: (ROOT / p).stat().st_size for p in paths if (ROOT / p).is_file()}


def test_tracked_files_leave_room_for_the_wheels_on_the_gpu_machine():
    sizes = _tracked_sizes()
    total = sum(sizes.values()) / 2**20
    largest = sorted(sizes.items(), key=lambda kv: -kv[1])[:5]
    assert total <= LIMIT_MIB, (f"tracked files hold {total:.1f} MiB, over {LIMIT_MIB} MiB: the tree would not "
                                f"travel to the GPU machine with the wheels; largest: {largest}")
