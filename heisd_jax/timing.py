"""How time is measured, in one place: a piece of JAX code timed three ways, and a run's wall
time split into named phases.

- wall clock per call (`timed`, `wall_seconds`, `median_seconds`): a jitted call blocked
  on, after an untimed warm-up call; what the benchmark scripts report;
- in-graph marginal cost (`in_graph_ms`): the piece looped n1 and n2 times inside one
  compiled program, the difference per run; what the cost model's tables hold (a decode
  pays one dispatch per action, not per pass);
- per kernel (`trace_calls`, `kernel_summary`): a `jax.profiler` trace summarised per
  device timeline (experiments/studies/trace_decode.py, experiments/profile.py); `write_hlo` keeps
  the optimised HLO that names those kernels (its fusions);
- a run's phases (`Phases`, `split_text`): an entry point's wall time as named parts that sum
  to it, printed as one line, `time: 12s = compile 3s (2 programs) + run 9s`, the line
  experiments/build_target.py records per stage (collect_demos, train, evaluate print it).
"""

from __future__ import annotations

import collections
import dataclasses
import gzip
import json
import functools
import re
import time
from pathlib import Path
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np


def timed(fn):
    """(fn()'s result, blocked on; the wall-clock seconds of the call)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


def repeated(fn, reps: int, first_counts_s: float = float("inf")):
    """(the last call's result, blocked on; the wall-clock seconds of each of `reps` timed calls
    of fn()), after one untimed call (compilation and warm-up excluded), unless that first call
    took `first_counts_s` or more: then it is the first repetition (a long call's one-time
    costs are negligible in it, and a call saved is worth its time)."""
    out, first = timed(fn)
    seconds = [first] if first >= first_counts_s else []
    while len(seconds) < reps:
        out, s = timed(fn)
        seconds.append(s)
    return out, seconds


def wall_seconds(fn, reps: int) -> list[float]:
    """Wall-clock of each of `reps` calls of fn() (results blocked on), after one untimed
    call (compilation and warm-up excluded)."""
    return repeated(fn, reps)[1]


def median_seconds(fn, reps: int) -> float:
    """Median of `wall_seconds`."""
    return float(np.median(wall_seconds(fn, reps)))


SLOW_PIECE_S, SLOW_REPS = 5e-3, 3  # `in_graph_ms` stops after SLOW_REPS pairs for pieces above 5 ms


def in_graph_ms(fn: Callable, args: tuple, n: tuple[int, int] = (2, 12), reps: int = 7) -> float:
    """Marginal cost in ms of one `fn(*args)` inside a compiled program: the median over
    `reps` back-to-back pairs of (n[1] runs - n[0] runs) / (n[1] - n[0]).

    The piece runs inside one jitted loop n[0] and n[1] times (one compile, the trip count is
    an argument), so the ~0.1-1.5 ms of dispatch per jitted call is not counted per run. The
    loop carries its inputs through an optimization barrier, so XLA can neither hoist the
    work out of the loop nor drop it. The median over pairs, since at batch 1 a piece costs
    0.03-0.4 ms and one pair of runs is that noisy; a piece above 5 ms (a 7B model's pass)
    stops after 3 pairs. Calls with the same `fn` object share one compiled loop."""
    return _in_graph(fn, args, n, reps, keep_output=False)[0]


def in_graph(fn: Callable, args: tuple, n: tuple[int, int] = (2, 12), reps: int = 7):
    """(`in_graph_ms`, fn(*args)'s output): the output comes out of the timed loop itself, so
    a caller that needs both (a decode's tokens, its rounds) pays one compile, not two; at a
    7B model's size a compile costs tens of seconds."""
    return _in_graph(fn, args, n, reps, keep_output=True)


def _in_graph(fn, args, n, reps, keep_output):
    if not 1 <= n[0] < n[1]:
        raise ValueError(f"need 1 <= n[0] < n[1] runs, got {n}")
    f = _looped(fn, keep_output)

    def seconds(count):
        return timed(lambda: f(count, args))[1]
    (_, out), _ = timed(lambda: f(n[1], args))  # compile + warm-up
    diffs = []
    for _ in range(reps):
        diffs.append(seconds(n[1]) - seconds(n[0]))
        if len(diffs) == SLOW_REPS and np.median(diffs) / (n[1] - n[0]) > SLOW_PIECE_S:
            break  # a slow piece (a large model's pass) is not noisy at this scale: spare the device
    return 1e3 * max(float(np.median(diffs)), 0.0) / (n[1] - n[0]), out


@functools.lru_cache(maxsize=64)
def _looped(fn: Callable, keep_output: bool):
    def loop(count, args):
        def body(_, carry):
            args, acc, last = carry
            out = fn(*args)
            args, out = jax.lax.optimization_barrier((args, out))
            leaf = jax.tree.leaves(out)[0]
            return args, acc + jnp.ravel(leaf)[0].astype(jnp.float32), out if keep_output else last
        last = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(fn, *args)) if keep_output else ()
        _, acc, last = jax.lax.fori_loop(0, count, body, (args, jnp.zeros((), jnp.float32), last))
        return acc, last
    return jax.jit(loop)


def trace_calls(fn, calls: int, directory: str | Path) -> Path | None:
    """Runs fn() `calls` times under `jax.profiler` (after nothing else: warm it up first);
    returns the Perfetto JSON the trace wrote (None if the profiler wrote none)."""
    directory = Path(directory)
    with jax.profiler.trace(str(directory), create_perfetto_trace=True):
        for _ in range(calls):
            jax.block_until_ready(fn())
    found = sorted(directory.glob("**/perfetto_trace.json.gz"))
    return found[-1] if found else None


def write_hlo(fn, args: tuple, path: str | Path) -> Path:
    """Writes jitted `fn`'s optimised HLO for `args` to `path` (gzipped text), where a trace's
    kernel names (its fusions) can be looked up; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wt") as f:
        f.write(fn.lower(*args).compile().as_text())
    return path


def _timelines(path: str | Path) -> dict[str, list[dict]]:
    """A Perfetto trace's complete ("X") events per timeline, "process | thread", in time order."""
    events = json.load(gzip.open(path))["traceEvents"]
    procs, threads = {}, {}
    for e in events:
        if e.get("ph") == "M" and e.get("name") == "process_name":
            procs[e["pid"]] = e["args"]["name"]
        if e.get("ph") == "M" and e.get("name") == "thread_name":
            threads[(e["pid"], e["tid"])] = e["args"]["name"]
    lines = collections.defaultdict(list)
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            lines[f"{procs.get(e['pid'], '')} | {threads.get((e['pid'], e.get('tid')), '')}"].append(e)
    return {line: sorted(evs, key=lambda e: e["ts"]) for line, evs in lines.items()}


def _is_device(line: str) -> bool:
    proc, _, thread = line.partition(" | ")
    return proc.startswith("/device:") or thread.startswith("tf_XLA")


def kernel_summary(path: str | Path, calls: int, top: int) -> dict:
    """Per device timeline of a Perfetto trace (a GPU's process/stream, or the CPU's XLA
    threads): {"total_ms": summed event time per call, "count": events per call, "top":
    [(event name, ms per call)], largest first, "launches": {top event name: events per call}}
    (a kernel launched once per layer shows the layer count). Event times are summed as
    recorded (nested events add up)."""
    out = {}
    for line, evs in _timelines(path).items():
        if _is_device(line):
            c, n = collections.Counter(), collections.Counter()
            for e in evs:
                c[e["name"]] += e["dur"] / 1e3 / calls  # us -> ms per call
                n[e["name"]] += 1
            most = c.most_common(top)
            out[line] = {"total_ms": sum(c.values()), "count": len(evs) / calls, "top": most,
                         "launches": {name: n[name] / calls for name, _ in most}}
    return out


def device_gaps(path: str | Path, min_ms: float = 0.5, top: int = 10) -> dict[str, list[dict]]:
    """Per device timeline of a Perfetto trace, its `top` longest idle stretches of at least
    `min_ms` between the first and the last kernel, longest first: {"start_ms" (from the
    timeline's first kernel), "ms", "after", "before" (the kernels around it), "host": the
    innermost host event that covers most of the stretch, i.e. what the device waited for (a
    CUDA-graph launch, a host sync, argument handling), "host_ms" its duration, or None}. At
    batch 1 a large model's call can be mostly such waits; the kernels alone do not show them."""
    lines = _timelines(path)
    host = [e for line, evs in lines.items() if not _is_device(line) for e in evs]
    out = {}
    for line, evs in lines.items():
        if not _is_device(line) or not evs:
            continue
        t0, gaps = evs[0]["ts"], []
        end, last = t0 + evs[0]["dur"], evs[0]["name"]  # where the device's work so far ends, and its kernel
        for e in evs[1:]:
            if e["ts"] - end >= min_ms * 1e3:
                gaps.append((end, e["ts"], last, e["name"]))
            if e["ts"] + e["dur"] >= end:
                end, last = e["ts"] + e["dur"], e["name"]
        rows = []
        for a, b, after, before in sorted(gaps, key=lambda g: g[0] - g[1])[:top]:
            covering = [h for h in host if min(b, h["ts"] + h["dur"]) - max(a, h["ts"]) >= 0.5 * (b - a)]
            inner = min(covering, key=lambda h: h["dur"], default=None)
            rows.append({"start_ms": (a - t0) / 1e3, "ms": (b - a) / 1e3, "after": after, "before": before,
                         "host": inner["name"] if inner else None, "host_ms": inner["dur"] / 1e3 if inner else None})
        out[line] = rows
    return out


_HOST_LOOP = re.compile(r"^(cond|conditional|while)(\.\d+)?$")  # XLA's control-flow thunks, named as in the HLO


def host_control(path: str | Path, calls: int) -> dict:
    """What a traced program's host did per call to drive the device (XLA's GPU runtime): the
    conditionals and while loops it ran itself ("conditionals": {name: runs per call}; one that
    a CUDA graph holds runs on the device and is not here), the device-to-host copies among
    them ("syncs": each is a predicate or trip count the host waits for, and the device drains
    for), and the CUDA-graph launches ("graph_launches" per call, "graph_launch_ms" of host time
    per call) and updates ("graph_update_ms"). A graph launch costs host time roughly in
    proportion to its nodes, and the device idles through it when nothing is queued."""
    runs, n, ms = collections.Counter(), collections.Counter(), collections.Counter()
    for line, evs in _timelines(path).items():
        if _is_device(line):
            continue
        for e in evs:
            name = e["name"]
            if _HOST_LOOP.match(name):
                runs[name] += 1
            elif name == "MemcpyD2H":
                n["syncs"] += 1
            elif name.startswith("cuGraphLaunch"):
                n["graph_launches"] += 1
                ms["graph_launch_ms"] += e["dur"] / 1e3
            elif name == "command_buffer::update":
                ms["graph_update_ms"] += e["dur"] / 1e3
    return {"conditionals": {k: v / calls for k, v in sorted(runs.items())},
            "syncs": n["syncs"] / calls, "graph_launches": n["graph_launches"] / calls,
            "graph_launch_ms": ms["graph_launch_ms"] / calls, "graph_update_ms": ms["graph_update_ms"] / calls}


def split_text(total: float, parts: Mapping[str, float], notes: Mapping[str, str] | None = None,
               label: str = "") -> str:
    """A run's time split as its one printed line, `time: {total}s {label} = {name} {seconds}s
    ({note}) + ...`: whole seconds, the parts in the order given, a part's note in parentheses
    after it, no ` = ...` without parts. The one format of that line, which
    experiments/build_target.py parses out of each stage's output."""
    notes = notes or {}
    head = f"time: {total:.0f}s" + (f" {label}" if label else "")
    if not parts:
        return head
    return head + " = " + " + ".join(f"{name} {sec:.0f}s" + (f" ({notes[name]})" if notes.get(name) else "")
                                     for name, sec in parts.items())


@dataclasses.dataclass
class Phases:
    """A run's wall time split into named phases: `lap(name)` adds the seconds since the last
    lap (or since `mark`, the run's start) to `name`, so the phases cover the run without gaps
    or overlaps and sum to its wall time. `seconds` given up front fixes the order of the
    printed parts (a phase lapped first may come later); `notes` are printed beside them."""

    mark: float = dataclasses.field(default_factory=time.perf_counter)  # perf_counter() of the last lap
    seconds: dict[str, float] = dataclasses.field(default_factory=dict)
    notes: dict[str, str] = dataclasses.field(default_factory=dict)

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self.mark
        self.mark = now

    def line(self) -> str:
        """`split_text` of the phases, their sum the total."""
        return split_text(sum(self.seconds.values()), self.seconds, self.notes)
