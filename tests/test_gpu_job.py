"""experiments/gpu_job.sh, with a stand-in `nvidia-smi`: in per-gpu mode command i runs on GPU i
(its own CUDA_VISIBLE_DEVICES, $OUT folder and compilation cache), all of them before the
script returns, and more commands than GPUs are refused before any runs; a poll brings back
the files it names, every small result file (JSON, logs) and, always, a build's newest
finished policy."""

import io
import os
import shutil
import subprocess
import tarfile
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "gpu_job.sh"


def _run(tmp_path, *args):
    fake = tmp_path / "bin"
    fake.mkdir(exist_ok=True)
    smi = fake / "nvidia-smi"
    smi.write_text('#!/bin/sh\necho "GPU 0: H200 (UUID: a)"\necho "GPU 1: H200 (UUID: b)"\n')
    smi.chmod(0o755)
    env = dict(os.environ, PATH=f"{fake}:{os.environ['PATH']}", OUT=str(tmp_path / "out"), GPU_JOB_SITE_READY="1",
               JAX_COMPILATION_CACHE_DIR=str(tmp_path / "cache"))
    return subprocess.run(["bash", str(SCRIPT), "per-gpu", *args], env=env, capture_output=True, text=True)


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_per_gpu_runs_command_i_on_gpu_i(tmp_path):
    write = 'echo "$CUDA_VISIBLE_DEVICES $JAX_COMPILATION_CACHE_DIR" > "$0"'
    r = _run(tmp_path, "--", "sh", "-c", write, "$OUT/where.txt", "--", "sh", "-c", write + "; exit 3", "$OUT/where.txt")
    assert r.returncode == 3, r.stderr  # a failing command's status comes back
    for i in (0, 1):
        folder = tmp_path / "out" / f"gpu{i}"
        assert (folder / "where.txt").read_text().split() == [str(i), f"{tmp_path / 'cache'}_gpu{i}"]
        assert f"== exit {3 * i}" in (folder / "job.log").read_text()
        assert f"==== GPU {i}" in r.stdout


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_per_gpu_refuses_more_commands_than_gpus(tmp_path):
    r = _run(tmp_path, "--", "touch", "$OUT/a", "--", "touch", "$OUT/b", "--", "touch", "$OUT/c")
    assert r.returncode == 2 and "3 commands for 2 GPUs" in r.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_per_gpu_command_named_gpus(tmp_path):
    write = 'echo "$CUDA_VISIBLE_DEVICES" > "$0"'
    r = _run(tmp_path, "--", "@0,1", "sh", "-c", write, "$OUT/where.txt", "--", "sh", "-c", write, "$OUT/where.txt")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out" / "gpu0" / "where.txt").read_text().split() == ["0,1"]  # @GPUS given
    assert (tmp_path / "out" / "gpu1" / "where.txt").read_text().split() == ["1"]  # command i on GPU i


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_poll_packs_named_and_small_result_files_and_the_builds_newest_finished_policy(tmp_path):
    work = tmp_path / "work"
    build = work / "out" / "b"
    for path in ("logs/train1.log", "vla1/0/params", "vla2/0/params", "vla3/partial"):  # vla3 still being written
        (build / path).parent.mkdir(parents=True, exist_ok=True)
        (build / path).write_text(path)
    (build / "build.json").write_text("{}")
    (work / "out" / "profile.json").write_text("{}")
    (work / "out" / "job.log").write_text("== exit 0\n")
    (work / "out" / "gpu0").mkdir()
    (work / "out" / "gpu0" / "eval_ar.json").write_text("{}")  # a result nobody named
    (work / "out" / "gpu0" / "trace.json").write_bytes(b" " * (3 << 20))  # too large to come back unnamed
    (build / "eval_ar_fresh.json").write_bytes(b" " * (3 << 20))  # large, but the build's: it comes back
    for dataset in ("demos", "fresh_demos"):
        (build / dataset).mkdir()
        (build / dataset / "meta.json").write_text("{}")  # a dataset's
    (work / "pid").write_text("999999999")  # a job that has ended
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "nvidia-smi").write_text("#!/bin/sh\n")
    (fake / "nvidia-smi").chmod(0o755)
    env = dict(os.environ, PATH=f"{fake}:{os.environ['PATH']}", OUT=str(tmp_path / "back"), GPU_JOB_WORK=str(work))
    (tmp_path / "back").mkdir()
    r = subprocess.run(["bash", str(SCRIPT), "poll", "0", "profile.json", "missing.json"], env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "ENDED" in r.stdout and "pack: no missing.json" in r.stdout
    (tmp_path / "back" / "results.tar.part-zz").write_bytes(b"stale")  # an earlier call's part in the same folder
    parts = sorted((tmp_path / "back").glob("results-*.tar.part-*"))
    assert parts and len({p.name.split(".part-")[0] for p in parts}) == 1  # one archive, named in the log
    assert f"packed: {parts[0].name.split('.part-')[0]}.part-*" in r.stdout
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts))) as tar:
        names = {n.rstrip("/") for n in tar.getnames()}
    assert {"profile.json", "b/build.json", "b/logs/train1.log", "b/vla2/0/params", "b/eval_ar_fresh.json", "job.log",
            "gpu0/eval_ar.json"} <= names
    assert not any(n.startswith(("b/vla1", "b/vla3", "b/demos", "b/fresh_demos", "gpu0/trace")) for n in names)


def _small_repo(tmp_path):
    """A tree holding gpu_job.sh alone: `start` copies the tree its script is in."""
    repo = tmp_path / "repo"
    (repo / "experiments").mkdir(parents=True)
    shutil.copy(SCRIPT, repo / "experiments" / "gpu_job.sh")
    return repo


@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("tar") is None, reason="needs bash and tar")
def test_start_runs_the_job_from_its_own_copy_of_the_tree(tmp_path):
    """Each device call replaces the working tree; a background job must not see that happen."""
    repo = _small_repo(tmp_path)
    (repo / "pkg.txt").write_text("the tree at start")
    (repo / "go").touch()
    work = tmp_path / "work"
    env = dict(os.environ, GPU_JOB_WORK=str(work), GPU_JOB_SITE_READY="1", GPU_JOB_START_WAIT="0")
    job = "while [ -e go ]; do sleep 0.1; done; cat pkg.txt > $OUT/seen.txt"  # waits until the tree has changed
    r = subprocess.run(["bash", str(repo / "experiments" / "gpu_job.sh"), "start", "--", "sh", "-c", job], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    (repo / "pkg.txt").unlink()  # the next call's copy of the tree, half made
    (work / "src" / "go").unlink()
    pid = int((work / "pid").read_text())
    for _ in range(300):
        if not Path(f"/proc/{pid}").exists():
            break
        subprocess.run(["sleep", "0.1"])
    assert (work / "out" / "seen.txt").read_text() == "the tree at start"
    assert "== exit 0" in (work / "out" / "job.log").read_text()


@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("tar") is None, reason="needs bash and tar")
def test_start_empties_the_output_folder_unless_told_to_keep_it(tmp_path):
    """GPU_JOB_KEEP=1 lets a failed build start again in place, its datasets still there."""
    work = tmp_path / "work"
    (work / "out" / "build").mkdir(parents=True)
    (work / "out" / "build" / "demos").write_text("collected")
    script = _small_repo(tmp_path) / "experiments" / "gpu_job.sh"
    for keep, survives in (("1", True), ("", False)):
        env = dict(os.environ, GPU_JOB_WORK=str(work), GPU_JOB_SITE_READY="1", GPU_JOB_START_WAIT="0", GPU_JOB_KEEP=keep)
        r = subprocess.run(["bash", str(script), "start", "--", "true"], env=env, capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 0, r.stderr
        assert (work / "out" / "build" / "demos").exists() == survives
        pid = int((work / "pid").read_text())
        for _ in range(300):  # the next start refuses while a job runs
            if not Path(f"/proc/{pid}").exists():
                break
            subprocess.run(["sleep", "0.1"])
