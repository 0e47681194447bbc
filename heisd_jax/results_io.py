"""Result files: atomic JSON writes and resumable loads that refuse foreign settings."""

from __future__ import annotations

import json
import os
from pathlib import Path


def write_json_atomic(path: str | os.PathLike, obj) -> None:
    """Writes JSON via a temporary file and rename: a crash leaves the old file intact."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_resumable(path: str | os.PathLike, settings: dict) -> dict:
    """Per-episode results of an earlier run with identical `settings`, or {} if none.
    Raises ValueError if the file holds a run with other settings or is not ours."""
    path = Path(path)
    if not path.exists():
        return {}
    try:
        with open(path) as f:
            data = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} exists but is not a readable results file ({e}); choose another --out") from e
    if not isinstance(data, dict) or data.get("settings") != settings:
        raise ValueError(
            f"{path} holds results of other settings ({data.get('settings') if isinstance(data, dict) else '?'}); "
            f"refusing to overwrite it: choose another --out"
        )
    return data.get("episodes", {})
