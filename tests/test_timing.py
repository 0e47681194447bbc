"""heisd_jax.timing: per-kernel trace summaries (behind experiments/studies/trace_decode.py), a
traced jitted call showing up on a device timeline with its time split per call; and a run's
phases, printed as the `time:` line experiments/build_target.py records."""

import gzip
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import timing


# A synthetic trace's timelines: a GPU stream (pid 1, tid 7) and a host thread (pid 2, tid 3).
_META = [{"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
         {"ph": "M", "name": "thread_name", "pid": 1, "tid": 7, "args": {"name": "Stream #7"}},
         {"ph": "M", "name": "process_name", "pid": 2, "args": {"name": "/host:CPU"}},
         {"ph": "M", "name": "thread_name", "pid": 2, "tid": 3, "args": {"name": "python"}}]


def _x(pid, tid, name, ts, dur):
    """A complete event of `dur` us at `ts` us."""
    return {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": ts, "dur": dur}


def test_kernel_summary_of_a_traced_call(tmp_path):
    f = jax.jit(lambda x: jnp.tanh(x @ x.T).sum(0))
    x = jnp.ones((384, 384), jnp.float32)
    jax.block_until_ready(f(x))  # compiled before the trace
    path = timing.trace_calls(lambda: f(x), 3, tmp_path / "three")
    assert path is not None and path.name == "perfetto_trace.json.gz", "the profiler wrote no Perfetto trace"
    whole = timing.kernel_summary(path, calls=1, top=5)
    per_call = timing.kernel_summary(path, calls=3, top=5)
    assert whole, "no device timeline in the trace"
    for line in whole.values():
        assert line["total_ms"] > 0 and 1 <= len(line["top"]) <= 5
        assert [ms for _, ms in line["top"]] == sorted((ms for _, ms in line["top"]), reverse=True)
    # Per-call figures: the same events, each divided by the number of calls.
    assert per_call.keys() == whole.keys()
    for name, line in whole.items():
        assert per_call[name]["total_ms"] == pytest.approx(line["total_ms"] / 3)
        assert line["count"] >= len(line["top"]) and per_call[name]["count"] == pytest.approx(line["count"] / 3)
        assert [k for k, _ in per_call[name]["top"]] == [k for k, _ in line["top"]]
        np.testing.assert_allclose([ms for _, ms in per_call[name]["top"]], [ms / 3 for _, ms in line["top"]])


def test_write_hlo_keeps_the_optimised_program_that_names_the_kernels(tmp_path):
    f = jax.jit(lambda x: jnp.tanh(x @ x.T).sum(0))
    x = jnp.ones((64, 64), jnp.float32)
    path = timing.write_hlo(f, (x,), tmp_path / "sub" / "f.hlo.txt.gz")
    with gzip.open(path, "rt") as fh:
        text = fh.read()
    assert text.startswith("HloModule") and "tanh" in text
    assert text == f.lower(x).compile().as_text()  # the compiled program, not the unoptimised one


def test_in_graph_returns_the_pieces_output_from_its_timed_loop():
    def piece(w, x):
        return {"y": jnp.tanh(x @ w), "n": jnp.sum(x > 0)}
    w, x = jnp.eye(16) * 0.5, jnp.arange(32.0).reshape(2, 16) - 8
    ms, out = timing.in_graph(piece, (w, x), n=(1, 3), reps=2)
    assert ms >= 0
    ref = jax.jit(piece)(w, x)
    np.testing.assert_allclose(np.asarray(out["y"]), np.asarray(ref["y"]), rtol=1e-6)
    assert int(out["n"]) == int(ref["n"])
    with pytest.raises(ValueError, match="1 <= n\\[0\\] < n\\[1\\]"):
        timing.in_graph_ms(piece, (w, x), n=(0, 3))


def test_device_gaps_name_what_the_device_waited_for(tmp_path):
    """A synthetic trace: kernels at 0-1 ms and 6-7 ms and 7.2-8 ms on a GPU stream, a host
    call spanning all of it and, inside, a 4.9 ms graph launch over the first idle stretch."""
    events = _META + [_x(1, 7, "conv", 0, 1000), _x(1, 7, "gemm", 6000, 1000), _x(1, 7, "tail", 7200, 800),
                     _x(2, 3, "jit_act", 0, 9000), _x(2, 3, "cuGraphLaunch (CudaGraph:17)", 1100, 4900)]
    path = tmp_path / "t.json.gz"
    with gzip.open(path, "wt") as f:
        json.dump({"traceEvents": events}, f)
    gaps = timing.device_gaps(path, min_ms=0.1)
    assert list(gaps) == ["/device:GPU:0 | Stream #7"]
    first, second = gaps["/device:GPU:0 | Stream #7"]
    assert first == {"start_ms": 1.0, "ms": 5.0, "after": "conv", "before": "gemm",
                     "host": "cuGraphLaunch (CudaGraph:17)", "host_ms": 4.9}
    assert second["ms"] == pytest.approx(0.2) and second["host"] == "jit_act"  # only the call covers it
    assert timing.device_gaps(path, min_ms=1.0)["/device:GPU:0 | Stream #7"] == [first]
    summary = timing.kernel_summary(path, calls=1, top=3)["/device:GPU:0 | Stream #7"]
    assert summary["total_ms"] == pytest.approx(2.8)
    assert summary["launches"] == {"conv": 1, "gemm": 1, "tail": 1}
    with gzip.open(path, "wt") as f:  # the stream's kernels twice over, as in two calls
        json.dump({"traceEvents": events + [dict(e, ts=e["ts"] + 10_000) for e in events[4:7]]}, f)
    summary = timing.kernel_summary(path, calls=2, top=1)["/device:GPU:0 | Stream #7"]
    assert summary["top"] == [("conv", pytest.approx(1.0))] and summary["launches"] == {"conv": 1.0}


def test_host_control_counts_what_the_host_ran_of_a_call(tmp_path):
    """A synthetic trace of two calls: each runs a conditional on the host (its predicate read
    back), a while loop once, and two graph launches; the device's own copy is not the host's."""
    call = [_x(2, 3, "cond.45", 0, 900), _x(2, 3, "MemcpyD2H", 10, 20), _x(2, 3, "cuGraphLaunch (CudaGraph:4)", 50, 800),
            _x(2, 3, "command_buffer::update", 40, 100), _x(2, 3, "while.3", 900, 100),
            _x(2, 3, "cuGraphLaunch (CudaGraph:5)", 920, 200), _x(2, 3, "conditional_fusion", 1100, 5),
            _x(1, 7, "MemcpyD2H", 30, 5), _x(1, 7, "cond.45", 60, 5)]
    events = _META + call + [dict(e, ts=e["ts"] + 5000) for e in call]
    path = tmp_path / "t.json.gz"
    with gzip.open(path, "wt") as f:
        json.dump({"traceEvents": events}, f)
    got = timing.host_control(path, calls=2)
    assert got == {"conditionals": {"cond.45": 1.0, "while.3": 1.0}, "syncs": 1.0, "graph_launches": 2.0,
                   "graph_launch_ms": pytest.approx(1.0), "graph_update_ms": pytest.approx(0.1)}


def test_split_text_is_the_time_line_in_whole_seconds_parts_in_the_order_given():
    line = timing.split_text(12.4, {"run": 8.8, "compile": 3.6}, notes={"compile": "2 programs"})
    assert line == "time: 12s = run 9s + compile 4s (2 programs)"
    # Each figure rounded on its own (half to even), so the parts need not add up to the total shown.
    assert timing.split_text(2.5, {"a": 0.5, "b": 1.5, "c": 0.5}) == "time: 2s = a 0s + b 2s + c 0s"
    # An empty note prints nothing; a note of a part not given is not printed.
    assert timing.split_text(3, {"a": 1, "b": 2}, notes={"a": "", "z": "absent"}) == "time: 3s = a 1s + b 2s"
    assert timing.split_text(61.7, {}, label="wall") == "time: 62s wall"  # evaluate --compile_only
    assert (timing.split_text(100.2, {"compile": 40.4, "run": 50.6, "host": 9.2}, label="wall",
                              notes={"host": "start 3.1s, env and policy 4.0s, other 2.1s"})
            == "time: 100s wall = compile 40s + run 51s + host 9s (start 3.1s, env and policy 4.0s, other 2.1s)")


def test_phases_cover_the_run_so_their_sum_is_its_wall_time(monkeypatch):
    clock = iter([1.4, 2.0, 3.0, 3.3, 7.9])
    monkeypatch.setattr(timing.time, "perf_counter", lambda: next(clock))
    # Declared up front, compile..host print in that order whichever is lapped first.
    phases = timing.Phases(mark=0.0, seconds=dict(compile=0.0, run=0.0, fetch=0.0, host=0.0))
    for name in ("run", "compile", "run", "host", "run"):  # a phase lapped twice adds up
        phases.lap(name)
    assert phases.mark == 7.9
    assert list(phases.seconds) == ["compile", "run", "fetch", "host"]
    assert sum(phases.seconds.values()) == pytest.approx(7.9)  # no gaps, no overlaps: mark to the last lap
    assert phases.seconds == pytest.approx({"compile": 0.6, "run": 1.4 + 1.0 + 4.6, "fetch": 0.0, "host": 0.3})
    phases.notes.update(compile="1 programs, 0 loaded from the executable store",
                        run="2 batches over 1 devices", host="episodes sliced and written")
    assert phases.line() == ("time: 8s = compile 1s (1 programs, 0 loaded from the executable store) + run 7s "
                             "(2 batches over 1 devices) + fetch 0s + host 0s (episodes sliced and written)")
    # Undeclared phases print in the order first lapped (experiments/train.py's stages).
    clock = iter([0.4, 2.0, 2.6])
    phases = timing.Phases(mark=0.0, notes={"steps": "7 after the first"})
    for name in ("start", "load", "steps"):
        phases.lap(name)
    assert phases.line() == "time: 3s = start 0s + load 2s + steps 1s (7 after the first)"
