"""Sets XLA_FLAGS for MJX on CPU before JAX starts its backends.

* `--xla_cpu_use_fusion_emitters=false`: with jaxlib >= 0.7, XLA:CPU's fusion emitters make
  MJX ~13x slower on CPU.
* `--xla_cpu_multi_thread_eigen=false`: keeps XLA:CPU's Eigen kernels single-threaded.
  It does not prevent the known CPU hang of large rollouts, a deadlock inside jaxlib's
  batched LAPACK Cholesky on the intra-op pool (docs/evaluator.md).
On a GPU, one more: `--xla_gpu_load_autotune_results_from=checkpoints/xla_autotune.pbtxt`,
XLA's autotuning results for the shipped checkpoints' evaluation programs (which kernel each
fusion and matrix product uses; `experiments/ship_autotune.py` makes them). A compile finds its
kernels there instead of timing candidates, which is about a third of the AR rollout's XLA
compile, and every machine then builds the same program, so the same episodes. They are loaded
only where the installed jax, jaxlib and CUDA plugin are the versions that made them (recorded
in `xla_autotune.json` beside them; another version may not read the file) and JAX may use a
GPU; entries are keyed by GPU model and each fusion's HLO, so another GPU or program finds
nothing there and autotunes as usual. An explicit setting (`--xla_gpu_load_autotune_results_from=`
turns it off) is respected.
Some XLA builds (seen: jaxlib 0.11.2 with the CUDA 13 plugin) abort on a flag they do not
know, although its name still appears in their binaries. So whether each flag is accepted
is probed once, in one child process that starts JAX's CPU backend with the flags together
(XLA names every flag it does not know; one by one only where a child fails without naming
them), and the answer is cached per installed jax/jaxlib/plugin versions and JAX_PLATFORMS.
A user's own XLA_FLAGS are kept; an explicit setting of either flag is respected.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
from pathlib import Path
import re
import subprocess
import sys

FLAGS = {"xla_cpu_use_fusion_emitters": "false", "xla_cpu_multi_thread_eigen": "false"}


def cache_root() -> Path:
    """`heisd_jax.cache_dirs.cache_root`, which envs may not import (tests pin the two equal)."""
    if os.environ.get("HEISD_CACHE"):
        return Path(os.environ["HEISD_CACHE"]).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser() / "heisd_jax"


_CACHE = cache_root() / "xla_flag.json"
AUTOTUNE_FLAG = "xla_gpu_load_autotune_results_from"
SHIPPED_AUTOTUNE = Path(__file__).resolve().parents[1] / "checkpoints" / "xla_autotune.pbtxt"


def jax_versions() -> str:
    """The installed jax, jaxlib and GPU plugins, e.g. 'jax==0.11.2;jaxlib==0.11.2'."""
    versions = []
    for dist in importlib.metadata.distributions():
        name = (dist.metadata["Name"] or "").lower().replace("_", "-")
        if name in ("jax", "jaxlib") or name.startswith("jax-cuda") or name.startswith("jax-rocm"):
            versions.append(f"{name}=={dist.version}")
    return ";".join(sorted(set(versions)))


def _fingerprint() -> str:
    return jax_versions() + f"|JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS', '')}"


def gpu_possible() -> bool:
    """Whether JAX in this process may use a CUDA GPU: a CUDA plugin is installed and
    JAX_PLATFORMS, if set, names cuda or gpu. Starts no backend."""
    platforms = os.environ.get("JAX_PLATFORMS", "").lower()
    return "jax-cuda" in jax_versions() and (not platforms or any(p in platforms for p in ("cuda", "gpu")))


def shipped_autotune(path: Path | None = None) -> Path | None:
    """`path` (default SHIPPED_AUTOTUNE) if this process may load it: its record (`path` with
    .json) names the installed versions, a CUDA plugin is installed and JAX_PLATFORMS (if set)
    allows CUDA; else None."""
    path = path or SHIPPED_AUTOTUNE
    try:
        made_with = json.loads(path.with_suffix(".json").read_text())["versions"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if made_with != jax_versions() or not gpu_possible() or not path.is_file() \
            or any(c.isspace() for c in str(path)):  # XLA_FLAGS splits on whitespace
        return None
    return path


def record_programs(record: dict) -> list[dict]:
    """The programs ({"device", "command"}) whose entries a shipped-results record's file holds;
    a record made before it named each program's GPU (one "device" for all) is read as that GPU's."""
    return [p if isinstance(p, dict) else {"device": record.get("device", "unknown"), "command": p}
            for p in record.get("programs", [])]


def with_autotune_files(load: str, dump: str, flags: str = "") -> str:
    """XLA_FLAGS `flags` (e.g. the caller's) with any autotuning-results load or dump setting
    replaced by these (`experiments/ship_autotune.py`)."""
    own = (AUTOTUNE_FLAG, "xla_gpu_dump_autotune_results_to")
    kept = [f for f in flags.split() if not any(n in f for n in own)]
    return " ".join(kept + [f"--{AUTOTUNE_FLAG}={load}", f"--xla_gpu_dump_autotune_results_to={dump}"])


def _probe(flags: str) -> set[str] | None:
    """The flags of `flags` XLA does not know, as given: empty when a JAX process starts with
    XLA_FLAGS=flags; None when it fails without naming only flags of `flags` (say, a value XLA
    cannot read). XLA reads XLA_FLAGS as its first backend starts, names every unknown flag in
    one message and aborts, so one child answers for all, and the CPU backend alone answers:
    the child never starts a GPU's (seconds on a fresh machine)."""
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    try:
        r = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env, capture_output=True,
                           text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if r.returncode == 0:
        return set()
    named = re.search(r"Unknown flags? in XLA_FLAGS: (.*)", r.stderr)
    unknown = set(named.group(1).split()) if named else set()
    return unknown if unknown and unknown <= set(flags.split()) else None


def supported(flags: dict[str, str]) -> dict[str, bool]:
    """Which of `flags` (name -> value) the installed XLA accepts, each answer cached per
    installed jax/jaxlib/plugin versions and JAX_PLATFORMS. The flags not cached yet are probed
    together in one child process (a probe starts JAX's CPU backend: a second or more on a
    fresh machine's first run), and one by one only where that child fails without naming
    which flags XLA does not know."""
    keys = {name: f"--{name}={value}|{_fingerprint()}" for name, value in flags.items()}
    try:
        cache = json.loads(_CACHE.read_text())
    except (OSError, ValueError):
        cache = {}
    todo = {name: f"--{name}={flags[name]}" for name in flags if keys[name] not in cache}
    if todo:
        unknown = _probe(" ".join(todo.values()))
        if unknown is None and len(todo) > 1:
            cache.update({keys[name]: _probe(arg) == set() for name, arg in todo.items()})
        else:
            cache.update({keys[name]: unknown is not None and arg not in unknown for name, arg in todo.items()})
        try:
            _CACHE.parent.mkdir(parents=True, exist_ok=True)
            tmp = _CACHE.with_suffix(f".tmp{os.getpid()}")
            tmp.write_text(json.dumps(cache))
            os.replace(tmp, _CACHE)
        except OSError:
            pass
    return {name: bool(cache[keys[name]]) for name in flags}


# XLA_FLAGS as the user set them, before `configure` adds the project's own: results files
# record them (`experiments.cli.command_line`), since they change what a run measures.
USER_FLAGS = os.environ.get("XLA_FLAGS", "").strip()


def configure() -> None:
    wanted = {name: value for name, value in FLAGS.items() if name not in os.environ.get("XLA_FLAGS", "")}
    for name, ok in supported(wanted).items():
        if ok:
            os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --{name}={wanted[name]}").strip()
    current = os.environ.get("XLA_FLAGS", "")
    path = shipped_autotune()
    if path is not None and AUTOTUNE_FLAG not in current:
        os.environ["XLA_FLAGS"] = (current + f" --{AUTOTUNE_FLAG}={path}").strip()


LAPACK_CHOLESKY_MAX_FLOPS = 1e5  # per call; jaxlib splits a batch over the pool above ~2e5


def cholesky_without_lapack_on_cpu() -> None:
    """Lowers large batched `cholesky_p` calls on CPU to XLA's own Cholesky instead of
    jaxlib's batched LAPACK kernel. Above a FLOP threshold that kernel splits its batch
    (MJX factors every env's mass matrix and Newton Hessian) into tasks on XLA:CPU's
    intra-op pool and blocks until they finish; when two such calls run at once on a
    2-thread pool, no thread is left to run the tasks and the rollout deadlocks for good
    (docs/evaluator.md). Calls under half that threshold (a few envs) keep LAPACK, which is
    faster there and never splits, so small CPU runs compute exactly as before. GPU and TPU
    lowerings are untouched. Uses JAX's internal lowering registry: where it is not there,
    nothing changes."""
    try:
        from jax._src.interpreters import mlir
        from jax._src.lax import linalg
        xla_rule, lapack_rule = linalg._cholesky_lowering, linalg._cholesky_cpu_lowering  # noqa: SLF001
    except (ImportError, AttributeError):
        return

    def rule(ctx, operand):
        shape = ctx.avals_in[0].shape
        batch = 1
        for d in shape[:-2]:
            batch *= d
        flops = batch * shape[-1] ** 3 / 3
        return (lapack_rule if flops < LAPACK_CHOLESKY_MAX_FLOPS else xla_rule)(ctx, operand)

    mlir.register_lowering(linalg.cholesky_p, rule, platform="cpu")
