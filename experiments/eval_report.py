"""What `experiments.evaluate` prints when a run ends, as pure functions of the results file
it wrote: every kind of file (fresh, resumed, stopped earlier, run as AR, a static batch or a
refilled queue) is then checked without running a rollout (tests/test_eval_report.py)."""

from __future__ import annotations

from heisd_jax.timing import split_text


def final_report(data: dict, camera: bool, out: str) -> str:
    """The lines a finished run prints, from the results file it wrote (`data`): per suite,
    success and decoding counts; this run's speed, and every run's where it resumed others;
    where the wall time went and the compile's parts; `out`, the file's path."""
    summary, timing = data["summary"], data["timing"]
    lines = [f"\n{'suite':<10}{'episodes':>10}{'success':>10}{'steps/ep':>10}{'passes/act':>12}{'accept len':>12}"
             f"{'passes/ep':>11}"]
    for name, s in summary["suites"].items():
        cols = [s.get(k) for k in ("target_passes_per_action", "tokens_per_target_pass", "target_passes_per_episode")]
        passes, al, per_ep = ("-" if v is None else f"{v:.{d}f}" for v, d in zip(cols, (2, 2, 0)))
        lines.append(f"{name:<10}{s['episodes']:>10}{s['success_rate']:>10.3f}{s['mean_steps']:>10.1f}{passes:>12}"
                     f"{al:>12}{per_ep:>11}")
    if timing["control_steps"]:
        lines.append(f"{timing['ms_per_control_step']:.1f} ms per control step ({timing['num_envs']} envs: decode + "
                     f"physics{' + camera' if camera else ''}), compile {timing['compile_seconds']:.0f}s")
    a = timing.get("all_runs")
    if a and a["control_steps"]:
        lines.append(f"all {a['runs']} runs of this file: {a['ms_per_control_step']:.1f} ms per control step over "
                     f"{a['control_steps']} control steps, {a['wall_seconds']:.0f}s wall")
    host = timing["host_split"]
    lines.append(split_text(timing["wall_seconds"], {"compile": timing["compile_seconds"],
                                                     "run": timing["batch_seconds"], "host": timing["host_seconds"]},
                            notes={"host": f"start {host['start']:.1f}s, env and policy {host['setup']:.1f}s, "
                                           f"other {host['other']:.1f}s"}, label="wall"))
    if timing.get("compile_split"):
        lines.append(f"compile: {compile_text({**timing['compile_split'], 'total': timing['compile_seconds']})}")
    lines.append(f"results: {out}")
    return "\n".join(lines)


def compile_text(split: dict[str, float]) -> str:
    """The compile's seconds as words: a static batch's one program, or a queue's programs
    (`{program}_{stage}` keys; their XLA compiles overlap, so they add up to more than the total)."""
    def stages(pre: str) -> str:
        if f"{pre}store" in split and not split[f"{pre}trace"]:
            return f"loaded from the executable store in {split[f'{pre}store']:.1f}s (no tracing, lowering or XLA)"
        return (f"trace {split[f'{pre}trace']:.1f}s + lower {split[f'{pre}lower']:.1f}s + XLA "
                f"{split[f'{pre}xla']:.1f}s (or its load from the compilation cache)" +
                (f" + store {split[f'{pre}store']:.1f}s (keying and saving)" if f"{pre}store" in split else ""))

    def programs(tail: bool) -> list[str]:
        return [k[:-len("_trace")] for k in split if k.endswith("_trace") and k.startswith("tail_") == tail]

    if "trace" in split:
        return f"{split['total']:.1f}s: {stages('')}"
    parts = programs(False)
    total = {s: sum(split.get(f"{p}_{s}", 0.0) for p in parts) for s in ("trace", "lower", "xla")}
    text = (f"{split['total']:.1f}s wall for {len(parts)} programs, their XLA side by side (trace "
            f"{total['trace']:.1f}s + lower {total['lower']:.1f}s in turn, XLA {total['xla']:.1f}s in all): "
            + "; ".join(f"{p}: {stages(p + '_')}" for p in parts))
    if programs(True):
        text += ("; the tail's programs, beside the head's run: " +
                 "; ".join(f"{p}: {stages(p + '_')}" for p in programs(True)) +
                 f"; waited for {split.get('tail_wait', 0.0):.1f}s")
    return text
