"""Compiled rollouts on disk, keyed by what makes them, so a warm run skips tracing and lowering.

JAX's persistent compilation cache is keyed by the lowered program: before it can answer, a
warm run still traces the rollout in Python and lowers it to MLIR, which is most of a warm
start's compile (docs/evaluator.md). This store keys the compiled executable by what
determines the program instead, all of it known before tracing:

- the source of the `envs` and `heisd_jax` packages (every `.py` file's bytes);
- the versions of jax, jaxlib, its plugins, mujoco and mujoco-mjx; XLA_FLAGS (and the bytes of
  the files they name, such as autotuning results to load); the JAX settings
  that change what is traced or lowered; the devices (platform, kind, ids) and process count;
- the shapes, dtypes and shardings of the program's inputs (the parameters included);
- an `identity` from the caller for everything else the program closes over: the env's
  config and tasks, the policy's name and meta, the rollout's sizes, the method's settings,
  digests of the files it loaded (`file_digest`).

A key that misses compiles as usual (through JAX's cache) and stores the result; an entry
that cannot be read or loaded is a miss, never an error. An identity that cannot be described
stably (an object whose repr holds a memory address) keys nothing: the store is skipped.

Two traps of XLA:CPU (jaxlib 0.10) are designed around. An executable that JAX loaded from its
own compilation cache serializes without its kernels ("Function ... not found" when run), so
on a CPU a program to be stored is compiled with that cache bypassed (`compile_storable`: a
full compile once per key, then loads). And jaxlib sets its LAPACK kernels' pointers
only while lowering an op that calls them, so a process that loads without lowering sets them
first (`load`). Used on one process (`supported`); several hosts compile as usual.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib
import importlib.metadata
import io
import json
import logging
import os
from pathlib import Path
import pickle
import tempfile
import threading
import time
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from envs import _xla

FORMAT = 1  # bump when the entry layout changes
SUFFIX = ".jaxexe"
MAX_BYTES = 4 << 30  # the store's size, pruned least recently used first (an entry: 3-15 MB)
_PACKAGES = ("envs", "heisd_jax")  # whose source makes the programs
_DISTRIBUTIONS = ("mujoco", "mujoco-mjx", "numpy")  # beside jax, jaxlib and its plugins
_JAX_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_default_prng_impl",
                 "jax_threefry_partitionable", "jax_numpy_rank_promotion", "jax_numpy_dtype_promotion",
                 "jax_use_shardy_partitioner", "jax_enable_checks", "jax_debug_nans", "jax_disable_jit")
log = logging.getLogger(__name__)


class Undescribable(ValueError):
    """An identity holds an object without a stable description (its repr names a memory address)."""


def supported(platform: str | None = None) -> bool:
    """Whether executables are stored and loaded here: CPUs and GPUs, one process."""
    return (platform or jax.default_backend()) in ("cpu", "gpu", "cuda", "rocm") and jax.process_count() == 1


_bypass_lock = threading.Lock()
_bypass = {"depth": 0, "before": None}  # compiles inside `jax_cache_bypassed` now, and the setting they found


@contextlib.contextmanager
def jax_cache_bypassed():
    """Inside, JAX's persistent compilation cache is neither read nor written. Thread-safe:
    compiles in several threads bypass it together, and the last to leave restores it."""
    from jax._src import compilation_cache  # noqa: PLC0415

    with _bypass_lock:
        if _bypass["depth"] == 0:
            _bypass["before"] = jax.config.jax_enable_compilation_cache
            jax.config.update("jax_enable_compilation_cache", False)
            compilation_cache.reset_cache()  # JAX decides once whether the cache is used: decide again
        _bypass["depth"] += 1
    try:
        yield
    finally:
        with _bypass_lock:
            _bypass["depth"] -= 1
            if _bypass["depth"] == 0:
                jax.config.update("jax_enable_compilation_cache", _bypass["before"])
                compilation_cache.reset_cache()


def compile_storable(lowered, compiler_options: dict | None = None):
    """`lowered.compile(compiler_options)` for storing: on a CPU with JAX's compilation cache
    bypassed, since XLA:CPU executables that JAX loaded from it serialize without their kernels
    (module doc)."""
    if jax.default_backend() != "cpu":
        return lowered.compile(compiler_options)
    with jax_cache_bypassed():
        return lowered.compile(compiler_options)


class Staged(NamedTuple):
    """A program before XLA: loaded from a store (`compiled`) or traced and lowered
    (`lowered`), with the seconds each stage took so far (`split`: trace, lower, store)."""
    key: str | None  # its store key; None: not stored
    compiled: Any
    lowered: Any
    split: dict[str, float]

    @property
    def out_info(self):
        return (self.lowered if self.compiled is None else self.compiled).out_info


def stage(store: "ExecutableStore | None", identity: Any, jitted, inputs: tuple,
          key_inputs: tuple | None = None) -> Staged:
    """`jitted`'s program for `inputs`, loaded from `store` under `identity` and `key_inputs`'
    signature (default `inputs`) without tracing, else traced and lowered (in the caller's
    mesh context) for `finish`. With no store (or where stores are not `supported`) it is
    only traced and lowered."""
    t0 = time.perf_counter()
    key = store.key(identity, key_inputs or inputs) if store is not None and supported() else None
    compiled = store.load(key) if key else None
    if compiled is not None:  # no tracing, lowering or XLA
        return Staged(key, compiled, None, {"trace": 0.0, "lower": 0.0, "xla": 0.0, "store": time.perf_counter() - t0})
    t1 = time.perf_counter()
    traced = jitted.trace(*inputs)
    t2 = time.perf_counter()
    lowered = traced.lower()
    split = {"trace": t2 - t1, "lower": time.perf_counter() - t2}
    if key:
        split["store"] = t1 - t0
    return Staged(key, None, lowered, split)


def finish(store: "ExecutableStore | None", staged: Staged, compiler_options: dict | None = None,
           on_compiled: Callable[[], None] | None = None):
    """(`staged`'s program compiled by XLA and saved to `store` under its key, or as loaded;
    its seconds by stage, `xla` added). `on_compiled` runs between the compile and the save
    (the evaluator waits there for the other hosts, so that the slowest host's compile counts)."""
    if staged.compiled is not None:
        return staged.compiled, staged.split
    t0 = time.perf_counter()
    compiled = compile_storable(staged.lowered, compiler_options) if staged.key else \
        staged.lowered.compile(compiler_options)
    if on_compiled is not None:
        on_compiled()
    t1 = time.perf_counter()
    split = {**staged.split, "xla": t1 - t0}
    if staged.key:
        store.save(staged.key, compiled)
        split["store"] += time.perf_counter() - t1
    return compiled, split


def compile_or_load(store: "ExecutableStore | None", identity: Any, jitted, inputs: tuple,
                    compiler_options: dict | None = None):
    """(`jitted` compiled for `inputs`, whether it came from `store`): `stage` then `finish`.
    For a program outside `BatchRollout` that several processes compile alike, such as each
    DAgger round's collection."""
    staged = stage(store, identity, jitted, inputs)
    return finish(store, staged, compiler_options)[0], staged.compiled is not None


def describe(obj: Any) -> Any:
    """A JSON-able, process-independent description of `obj`: dataclasses by field, containers
    by item, arrays by shape, dtype and a digest of their bytes. Raises `Undescribable` for an
    object whose repr holds a memory address (a closure, an opaque handle)."""
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, float):
        return repr(obj)
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__type__": type(obj).__qualname__,
                **{f.name: describe(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, dict):
        return {"__dict__": sorted((json.dumps(describe(k), sort_keys=True), describe(v)) for k, v in obj.items())}
    if isinstance(obj, (list, tuple)):
        return {"__seq__": type(obj).__qualname__, "items": [describe(v) for v in obj]}
    if isinstance(obj, (np.ndarray, np.generic, jax.Array)):
        a = np.asarray(obj)
        return {"__array__": [list(a.shape), str(a.dtype), hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()]}
    text = repr(obj)
    if " at 0x" in text or "object at" in text:
        raise Undescribable(f"cannot key a compiled program on {type(obj).__qualname__}: its repr is {text[:80]!r}")
    return {"__repr__": type(obj).__qualname__, "text": text}


def file_digest(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes, or of a directory's files (relative names and bytes, sorted)."""
    path = Path(path)
    h = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    if not files:
        raise FileNotFoundError(f"nothing to digest at {path}")
    for p in files:
        h.update(str(p.relative_to(path) if p != path else p.name).encode() + b"\0")
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


@functools.cache
def source_digest() -> str:
    """sha256 over every `.py` file of the packages whose code makes the programs."""
    h = hashlib.sha256()
    for name in _PACKAGES:
        root = Path(importlib.import_module(name).__file__).parent
        for p in sorted(root.rglob("*.py")):
            h.update(f"{name}/{p.relative_to(root)}".encode() + b"\0" + p.read_bytes())
    return h.hexdigest()


@functools.cache
def _versions() -> str:
    """The installed jax, jaxlib, GPU plugins, mujoco, mujoco-mjx and numpy (fixed per process)."""
    others = []
    for name in _DISTRIBUTIONS:
        try:
            others.append(f"{name}=={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            others.append(f"{name}==none")
    return ";".join([_xla.jax_versions(), *others])


def environment() -> dict:
    """What outside the code changes a compiled program: versions, flags, JAX settings, devices."""
    devices = jax.devices()
    flags = os.environ.get("XLA_FLAGS", "")
    flag_files = {value: file_digest(value) for _, _, value in (f.partition("=") for f in flags.split())
                  if value and Path(value).is_file()}  # e.g. the autotuning results XLA loads
    return {"versions": _versions(), "XLA_FLAGS": flags, "flag_files": flag_files,
            "jax": {k: str(getattr(jax.config, k, None)) for k in _JAX_SETTINGS},
            "devices": [[d.platform, d.device_kind, d.id, d.process_index] for d in devices],
            "processes": jax.process_count()}


def input_signature(inputs: Any) -> Any:
    """The program's inputs as it sees them: tree structure, shapes, dtypes, weak types, shardings."""
    leaves, tree = jax.tree_util.tree_flatten(inputs)
    return {"tree": str(tree), "leaves": [[list(np.shape(x)), str(getattr(x, "dtype", type(x).__name__)),
                                           bool(getattr(x, "weak_type", False)), str(getattr(x, "sharding", ""))]
                                          for x in leaves]}


class ExecutableStore:
    """Compiled programs in `directory`, one file per key (written atomically). `identity`: what
    the caller knows makes its programs beyond what `BatchRollout` adds itself (a method's
    settings, digests of the files it loaded). After a save the directory is kept within
    `max_bytes`: the entries used longest ago (by modification time, which a load renews) go
    first, the one just written never."""

    def __init__(self, directory: str | os.PathLike, identity: Any = None, max_bytes: int = MAX_BYTES):
        self.directory = Path(directory).expanduser()
        self.identity = identity
        self.max_bytes = max_bytes

    def prune(self, keep: str | None = None) -> list[Path]:
        """Deletes the least recently used entries until the store fits `max_bytes` (never
        `keep`'s); returns the paths deleted."""
        entries = []
        for p in self.directory.glob(f"*{SUFFIX}"):
            try:
                st = p.stat()
            except FileNotFoundError:  # pruned by another process meanwhile
                continue
            entries.append((st.st_mtime, st.st_size, p))
        total, gone = sum(size for _, size, _ in entries), []
        for _, size, p in sorted(entries, key=lambda e: e[0]):
            if total <= self.max_bytes:
                break
            if keep is not None and p == self.path(keep):
                continue
            p.unlink(missing_ok=True)
            total -= size
            gone.append(p)
        return gone

    def key(self, identity: Any, inputs: Any) -> str | None:
        """The key of the program that `identity` names, called with `inputs`; None when the
        identity cannot be described stably (then nothing is stored or loaded)."""
        try:
            described = describe(identity)
        except Undescribable as e:
            log.warning("executable store skipped: %s", e)
            return None
        text = json.dumps({"format": FORMAT, "source": source_digest(), "environment": environment(),
                           "inputs": input_signature(inputs), "identity": described}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    def path(self, key: str) -> Path:
        return self.directory / f"{key}{SUFFIX}"

    def load(self, key: str | None):
        """The stored `jax.stages.Compiled` of `key`, or None (no entry, or one that fails to load)."""
        if key is None or not self.path(key).is_file():
            return None
        from jax.experimental import serialize_executable  # noqa: PLC0415

        try:
            with open(self.path(key), "rb") as f:
                fmt, payload, in_tree, out_tree = pickle.load(f)
            if fmt != FORMAT:
                return None
            if jax.default_backend() == "cpu":
                from jax._src.lax import linalg  # noqa: PLC0415

                linalg.initialize_lapack()  # the pointers lowering would have set (module doc)
            compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
            os.utime(self.path(key))  # used now: pruned last
            return compiled
        except Exception as e:  # noqa: BLE001  (a stale or truncated entry is a miss, and is rewritten)
            log.warning("executable store: cannot load %s (%s: %s); compiling", self.path(key), type(e).__name__, e)
            return None

    def save(self, key: str | None, compiled) -> bool:
        """Writes `compiled` under `key` (atomically: a crash leaves no partial entry). False when it
        cannot be serialized or written (a warning; the run goes on)."""
        if key is None:
            return False
        from jax.experimental import serialize_executable  # noqa: PLC0415

        try:
            payload, in_tree, out_tree = serialize_executable.serialize(compiled)
            buf = io.BytesIO()
            pickle.dump((FORMAT, payload, in_tree, out_tree), buf, protocol=pickle.HIGHEST_PROTOCOL)
            self.directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.directory, suffix=".tmp")
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(buf.getvalue())
                os.replace(tmp, self.path(key))
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
            self.prune(keep=key)
            return True
        except Exception as e:  # noqa: BLE001
            log.warning("executable store: not saved (%s: %s)", type(e).__name__, e)
            return False
