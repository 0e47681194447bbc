"""Sets XLA_FLAGS for fast MJX on CPU before JAX starts its backends.

With jaxlib >= 0.7, XLA:CPU's fusion emitters make MJX ~13x slower on CPU;
`--xla_cpu_use_fusion_emitters=false` restores the speed. Some XLA builds (seen: jaxlib
0.11.2 with the CUDA 13 plugin) abort on this flag as unknown, although its name still
appears in their binaries. So whether the flag is accepted is probed once, in a child
process that starts JAX's backends with it, and the answer is cached per installed
jax/jaxlib/plugin versions and JAX_PLATFORMS. A user's own XLA_FLAGS are kept; an explicit
setting of this flag is respected.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
from pathlib import Path

FLAG_NAME = "xla_cpu_use_fusion_emitters"
FLAG = f"--{FLAG_NAME}=false"
_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "heisd_jax" / "xla_flag.json"


def _fingerprint() -> str:
    versions = []
    for dist in importlib.metadata.distributions():
        name = (dist.metadata["Name"] or "").lower()
        if name in ("jax", "jaxlib") or name.startswith("jax-cuda") or name.startswith("jax_cuda") or name.startswith("jax-rocm"):
            versions.append(f"{name}=={dist.version}")
    return ";".join(sorted(versions)) + f"|JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS', '')}"


def _probe(flags: str) -> bool:
    env = dict(os.environ, XLA_FLAGS=flags)
    try:
        r = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env, capture_output=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return r.returncode == 0


def flag_supported() -> bool:
    key = _fingerprint()
    try:
        cache = json.loads(_CACHE.read_text())
    except (OSError, ValueError):
        cache = {}
    if key not in cache:
        cache[key] = _probe(FLAG)
        try:
            _CACHE.parent.mkdir(parents=True, exist_ok=True)
            tmp = _CACHE.with_suffix(f".tmp{os.getpid()}")
            tmp.write_text(json.dumps(cache))
            os.replace(tmp, _CACHE)
        except OSError:
            pass
    return bool(cache[key])


def configure() -> None:
    current = os.environ.get("XLA_FLAGS", "")
    if FLAG_NAME in current:
        return
    if flag_supported():
        os.environ["XLA_FLAGS"] = (current + " " + FLAG).strip()
