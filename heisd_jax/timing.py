"""Wall-clock helpers shared by the benchmark scripts and the cost-model calibration, and
per-kernel summaries of `jax.profiler` traces (experiments/trace_decode.py)."""

from __future__ import annotations

import collections
import gzip
import json
import time
from pathlib import Path

import jax
import numpy as np


def wall_seconds(fn, reps: int) -> list[float]:
    """Wall-clock of each of `reps` calls of fn() (results blocked on), after one untimed
    call (compilation and warm-up excluded)."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return times


def median_seconds(fn, reps: int) -> float:
    """Median of `wall_seconds`."""
    return float(np.median(wall_seconds(fn, reps)))


def trace_calls(fn, calls: int, directory: str | Path) -> Path | None:
    """Runs fn() `calls` times under `jax.profiler` (after nothing else: warm it up first);
    returns the Perfetto JSON the trace wrote (None if the profiler wrote none)."""
    directory = Path(directory)
    with jax.profiler.trace(str(directory), create_perfetto_trace=True):
        for _ in range(calls):
            jax.block_until_ready(fn())
    found = sorted(directory.glob("**/perfetto_trace.json.gz"))
    return found[-1] if found else None


def kernel_summary(path: str | Path, calls: int, top: int) -> dict:
    """Per device timeline of a Perfetto trace (a GPU's process/stream, or the CPU's XLA
    threads): {"total_ms": summed event time per call, "top": [(event name, ms per call)],
    largest first}. Event times are summed as recorded (nested events add up)."""
    events = json.load(gzip.open(path))["traceEvents"]
    procs, threads = {}, {}
    for e in events:
        if e.get("ph") == "M" and e.get("name") == "process_name":
            procs[e["pid"]] = e["args"]["name"]
        if e.get("ph") == "M" and e.get("name") == "thread_name":
            threads[(e["pid"], e["tid"])] = e["args"]["name"]
    by_line = collections.defaultdict(collections.Counter)
    for e in events:
        if e.get("ph") != "X" or "dur" not in e:
            continue
        proc, thread = procs.get(e["pid"], ""), threads.get((e["pid"], e.get("tid")), "")
        if proc.startswith("/device:") or thread.startswith("tf_XLA"):
            by_line[f"{proc} | {thread}"][e["name"]] += e["dur"] / 1e3 / calls  # us -> ms per call
    return {line: {"total_ms": sum(c.values()), "top": c.most_common(top)} for line, c in by_line.items()}
