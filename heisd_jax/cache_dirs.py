"""Where heisd-jax keeps what it measures or compiles once and reuses (cost tables, the XLA
flag probe, JAX's compilation cache): $HEISD_CACHE, else $XDG_CACHE_HOME/heisd_jax, else
~/.cache/heisd_jax. No heavy imports: `envs` reads it before JAX starts."""

from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    if os.environ.get("HEISD_CACHE"):
        return Path(os.environ["HEISD_CACHE"]).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser() / "heisd_jax"
