"""Result files: atomic JSON writes and resumable loads that refuse foreign settings."""

from __future__ import annotations

import gzip
import json
import os
import subprocess
import time
from pathlib import Path


def write_json_atomic(path: str | os.PathLike, obj) -> None:
    """Writes JSON via a temporary file and rename: a crash leaves the old file intact. A path
    ending in `.gz` is written gzipped (as the results committed under experiments/results are)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    text = json.dumps(obj, indent=1).encode()
    with open(tmp, "wb") as f:
        f.write(gzip.compress(text, mtime=0) if path.name.endswith(".gz") else text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_json(path: str | os.PathLike):
    """A JSON file, plain or gzipped (by its content, whatever its name); ValueError naming the
    path when it cannot be read as one."""
    try:
        raw = Path(path).read_bytes()
        return json.loads(gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw)
    except (OSError, EOFError, gzip.BadGzipFile, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a readable JSON file ({type(e).__name__}: {e})") from e


def commit(short: bool = True) -> str | None:
    """The repository's commit: $HEISD_COMMIT if set (a tree copied to another machine, whose
    .git is not its own), else git's HEAD (short or full hash); None outside a git checkout."""
    if os.environ.get("HEISD_COMMIT"):
        return os.environ["HEISD_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", *(["--short"] if short else []), "HEAD"], capture_output=True,
                              text=True, cwd=Path(__file__).resolve().parents[1], timeout=10).stdout.strip() or None
    except OSError:
        return None


def provenance(command: str) -> dict:
    """What a results file records about its making: the command, the short `commit`, the
    first device's kind and the date."""
    import jax  # noqa: PLC0415

    return {"command": command, "commit": commit(), "device": jax.devices()[0].device_kind,
            "date": time.strftime("%Y-%m-%d")}


def run_identity(settings: dict) -> dict:
    """What makes two evaluations' settings the same run: all of them but the paths of the
    files that their `contents` names by digest (the same checkpoint read from another folder,
    as a leased machine's job copies the tree, is the same run; another file at the same path
    is not). A path whose file was missing (digest None) stays."""
    digested = {k for k, v in settings.get("contents", {}).items() if v is not None}
    return {k: v for k, v in settings.items() if k not in digested}


def load_resumable(path: str | os.PathLike, settings: dict) -> dict:
    """Per-episode results of an earlier run of the same `settings` (`run_identity`), or {}
    if none. Raises ValueError if the file holds a run with other settings or is not ours."""
    return read_resumable(path, settings).get("episodes", {})


def read_resumable(path: str | os.PathLike, settings: dict) -> dict:
    """The whole results file of an earlier run of the same `settings`, or {} if none; the
    errors of `load_resumable`."""
    path = Path(path)
    if not path.exists():
        return {}
    try:
        data = read_json(path)
    except ValueError as e:
        raise ValueError(f"{path} exists but is not a readable results file ({e}); choose another --out") from e
    if not isinstance(data, dict) or not isinstance(data.get("settings"), dict) or (
            run_identity(data["settings"]) != run_identity(settings)):
        raise ValueError(
            f"{path} holds results of other settings ({data.get('settings') if isinstance(data, dict) else '?'}); "
            f"refusing to overwrite it: choose another --out"
        )
    return data


def earlier_runs(data: dict) -> list[dict]:
    """The timings of the runs that wrote a results file (`read_resumable`'s `data`), oldest
    first: its `timing.earlier` and then its own `timing` (a run resumed over it keeps them,
    so a file written over several leases keeps every run's speed). [] where it has none."""
    t = data.get("timing")
    if not isinstance(t, dict):
        return []
    return [*t.get("earlier", []), {k: v for k, v in t.items() if k not in ("earlier", "all_runs")}]


def all_runs(timings: list[dict]) -> dict:
    """The runs' timings summed: control steps, batch, compile and wall seconds, env steps,
    and the ms per control step over all of them."""
    out = {"runs": len(timings), **{k: sum(t.get(k, 0) for t in timings) for k in (
        "control_steps", "env_steps", "batch_seconds", "compile_seconds", "wall_seconds")}}
    if out["control_steps"]:
        out["ms_per_control_step"] = 1e3 * out["batch_seconds"] / out["control_steps"]
    return out


# --- sweeps: one JSON line per finished cell ----------------------------------------------

SWEEP_FORMAT = "heisd-jax-sweep-v1"


def cell_key(cell: dict) -> str:
    """Canonical identity of a sweep cell (method, its settings, suite, seed, batch size...)."""
    return json.dumps(cell, sort_keys=True, separators=(",", ":"))


class SweepFile:
    """A JSON-lines results file: a header line ({"format", "sweep": fixed settings}), then one
    record per finished cell ({"cell": {...}, ...}). Appends are flushed and fsynced line by
    line, so a crash can at worst leave one partial trailing line; opening the file detects
    it and cuts it off (that cell is redone), while damage anywhere else, or a header of
    other settings, is refused rather than overwritten. A new file is written with its first
    record (header and record at once), so a sweep refused or stopped before any cell ends
    leaves no file; its folder is made, and checked writable, when the file is opened."""

    def __init__(self, path: str | os.PathLike, sweep: dict):
        self.path = Path(path)
        self.sweep = sweep
        self.records: list[dict] = []
        self.repaired = False
        if self.path.is_dir():
            raise ValueError(f"{self.path} is a folder, not a results file; choose another --out")
        if self.path.exists() and self.path.stat().st_size:
            self._load()
        else:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                raise ValueError(f"{self.path}: cannot make its folder ({e}); choose another --out") from e
            if not os.access(self.path.parent, os.W_OK):
                raise ValueError(f"{self.path}: its folder is not writable; choose another --out")

    def _load(self):
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        complete, tail = lines[:-1], lines[-1]  # a file we wrote ends with a newline
        parsed = []
        for i, line in enumerate(complete):
            try:
                parsed.append(json.loads(line))
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                if i == len(complete) - 1 and not tail:  # a damaged last line: redo that cell
                    complete, tail = complete[:-1], line
                    break
                raise ValueError(f"{self.path}: line {i + 1} is damaged ({e}); not a trailing partial write, "
                                 f"refusing to touch the file: choose another --out") from e
        if not parsed or not isinstance(parsed[0], dict) or parsed[0].get("format") != SWEEP_FORMAT:
            raise ValueError(f"{self.path} is not a {SWEEP_FORMAT} results file; choose another --out")
        if parsed[0].get("sweep") != self.sweep:
            raise ValueError(f"{self.path} holds a sweep of other settings ({parsed[0].get('sweep')}); refusing to "
                             f"mix results: choose another --out")
        if tail:  # a partial trailing line (crash mid-write): drop it, keep everything before
            self.repaired = True
            write_json_lines_atomic(self.path, parsed)
        self.records = parsed[1:]

    def done(self) -> set[str]:
        return {cell_key(r["cell"]) for r in self.records}

    def append(self, record: dict) -> None:
        if cell_key(record["cell"]) in self.done():
            raise ValueError(f"cell already recorded: {record['cell']}")
        if not (self.path.exists() and self.path.stat().st_size):
            write_json_lines_atomic(self.path, [{"format": SWEEP_FORMAT, "sweep": self.sweep}, record])
            self.records.append(record)
            return
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.records.append(record)


def write_json_lines_atomic(path: Path, objs: list) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        for o in objs:
            f.write(json.dumps(o) + "\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_sweep(path: str | os.PathLike) -> tuple[dict, list[dict]]:
    """(sweep settings, records) of a sweep file, for reports (a partial trailing line is
    skipped, not repaired)."""
    lines = Path(path).read_text().split("\n")
    objs = []
    for i, line in enumerate(lines):
        if not line:
            continue
        try:
            objs.append(json.loads(line))
        except json.JSONDecodeError as e:
            if i >= len(lines) - 2:
                break
            raise ValueError(f"{path}: line {i + 1} is damaged ({e})") from e
    if not objs or objs[0].get("format") != SWEEP_FORMAT:
        raise ValueError(f"{path} is not a {SWEEP_FORMAT} results file")
    return objs[0]["sweep"], objs[1:]
