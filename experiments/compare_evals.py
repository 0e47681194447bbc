"""Closed-loop success of evaluations against a baseline evaluated on the same initial states:
per suite, the success rate, its difference from the baseline, and the paired counts (episodes
of one initial state that succeed under the baseline only / under the other only); per
evaluation, steps and target passes per episode (and the baseline's passes over its: the
saving per episode, longer episodes included), the steps its successful episodes took (mean
and 90th percentile: a policy that finishes tasks more slowly loses episodes to the time
limit), the share of skipped steps and whether every suite is within --tolerance points of
the baseline (the success guard of issue 23).

  python -m experiments.compare_evals experiments/results/eval_ar_7c71161_h100.json \\
      experiments/results/eval_heisd_fixed_target_h100.json.gz [MORE.json ...] [--tolerance=2]

Each file is an `experiments.evaluate --out` result; all must hold the same tasks with the
same number of episodes each (the evaluator's fixed initial states pair them). `--common_tasks`
compares on the tasks all of them hold, `--ended_only` on the episodes all of them have ended
(an evaluation cut mid-queue against a whole one).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from absl import app, flags

from experiments import cli
from heisd_jax import results_io

FLAGS = flags.FLAGS
flags.DEFINE_float("tolerance", 2.0, "Success guard: the largest drop below the baseline, in points, on any suite.")
flags.DEFINE_bool("common_tasks", False, "Compare on the tasks every evaluation holds (the others are named and left "
                  "out), e.g. a partial run against a whole baseline. Off: evaluations of other tasks are refused.")
flags.DEFINE_bool("ended_only", False, "Compare on the episodes every evaluation has ended (an evaluation cut "
                  "mid-queue against a whole one). Its rates lean high: a cut run's unended episodes are the ones "
                  "still running, the slow ones, among them its time-outs. Off: an unfinished evaluation is refused.")


def label(result: dict) -> str:
    """The method, the settings its command gave, and the commit it ran at."""
    s = dict(result.get("settings", {}))
    method = s.pop("method", "?")
    shown = {k: v for k, v in s.items()
             if k not in ("tasks", "episodes_per_task", "checkpoint", "drafter", "physics", "contents", "config")}
    physics = _physics_text(s.get("physics"))
    if physics:
        shown["physics"] = f"({physics})"
    settings = ",".join(f"{k}={Path(str(v)).name if k == 'datastore' else v}" for k, v in sorted(shown.items()))
    commit = result.get("commit")
    return method + (f":{settings}" if settings else "") + (f" @{commit[:7]}" if commit else "")


def _physics_text(recorded: dict | None) -> str:
    """The recorded physics' fields that differ from today's defaults ('' where none or none
    recorded)."""
    from envs import physics  # noqa: PLC0415

    if not recorded:
        return ""
    defaults = physics.PhysicsConfig()
    return ",".join(f"{k}={v}" for k, v in recorded.items() if getattr(defaults, k, None) != v)


def join(parts: list[dict]) -> dict:
    """One evaluation from evaluations of disjoint tasks with the same settings (the settings'
    task lists concatenated; per-task results and episodes side by side; the commit kept where
    all agree). ValueError naming the settings that differ or the tasks that repeat."""
    if len(parts) == 1:
        return parts[0]

    def same(settings: dict) -> dict:  # files named by their contents' digests, not the paths they were read from
        return {k: v for k, v in results_io.run_identity(settings).items() if k != "tasks"}
    first = same(parts[0].get("settings", {}))
    for i, p in enumerate(parts[1:], 1):
        s = same(p.get("settings", {}))
        if s != first:
            keys = sorted(k for k in set(s) | set(first) if s.get(k) != first.get(k))
            raise ValueError(f"cannot join evaluations of other settings (part {i + 1} differs in {', '.join(keys)})")
    seen: dict[str, int] = {}
    for i, p in enumerate(parts):
        for t in p["episodes"]:
            if t in seen:
                raise ValueError(f"cannot join evaluations that both hold task {t!r} (parts {seen[t] + 1} and {i + 1})")
            seen[t] = i
    commits = {p.get("commit") for p in parts}
    tasks = [t for p in parts for t in p.get("settings", {}).get("tasks") or p["episodes"]]
    return dict(settings=dict(parts[0]["settings"], tasks=tasks), episodes={t: e for p in parts for t, e in p["episodes"].items()},
                summary=dict(tasks={t: v for p in parts for t, v in p["summary"]["tasks"].items()}),
                commit=commits.pop() if len(commits) == 1 else None)


def common(results: list[dict]) -> tuple[list[dict], list[str]]:
    """The results restricted to the tasks all of them hold (in the first one's order), and
    the tasks left out."""
    keep = set.intersection(*(set(r["episodes"]) for r in results))
    order = results[0].get("settings", {}).get("tasks") or list(results[0]["episodes"])
    out = [_restricted(r, {t: r["episodes"][t] for t in order if t in keep}) for r in results]
    return out, sorted(set().union(*(set(r["episodes"]) for r in results)) - keep)


def _restricted(result: dict, episodes: dict[str, list]) -> dict:
    """`result` holding only `episodes` (task -> records, in the order to compare them): its
    settings' task list and its summary's tasks follow (a task not started has no summary)."""
    tasks = result["summary"]["tasks"]
    return dict(result, settings=dict(result.get("settings", {}), tasks=list(episodes)), episodes=episodes,
                summary=dict(result["summary"], tasks={t: tasks[t] for t in episodes if t in tasks}))


def ended(results: list[dict]) -> tuple[list[dict], int]:
    """The results restricted to the episodes (initial states) every one of them has ended,
    tasks with none dropped, and how many episodes were left out. ValueError where they are
    of other tasks or episode counts (`common` first restricts them to the shared tasks)."""
    first = results[0]["episodes"]
    if any({t: len(e) for t, e in r["episodes"].items()} != {t: len(e) for t, e in first.items()} for r in results):
        raise ValueError("the evaluations hold other tasks or episode counts: they are not paired "
                         "(--common_tasks compares on the tasks all of them hold)")
    order = results[0].get("settings", {}).get("tasks") or list(first)
    keep = {t: [i for i in range(len(first[t])) if all(r["episodes"][t][i] is not None for r in results)]
            for t in order}
    keep = {t: idx for t, idx in keep.items() if idx}
    out = [_restricted(r, {t: [r["episodes"][t][i] for i in idx] for t, idx in keep.items()}) for r in results]
    return out, sum(map(len, first.values())) - sum(map(len, keep.values()))


def with_unstarted(result: dict) -> dict:
    """`result` with a task its settings name but its episodes lack (a run cut before it
    started the task) given that many unended episodes (None), as a run cut mid-task has."""
    s = result.get("settings", {})
    missing = [t for t in s.get("tasks") or [] if t not in result["episodes"]]
    if not missing or not s.get("episodes_per_task"):
        return result
    return dict(result, episodes={**result["episodes"], **{t: [None] * s["episodes_per_task"] for t in missing}})


def load(arg: str) -> dict:
    """An evaluate result, or several joined with '+' (`join`)."""
    return join([with_unstarted(cli.load_eval_results(p)) for p in arg.split("+")])


def compare(base: dict, other: dict, tolerance: float) -> dict:
    """Per-suite and overall comparison of `other` with `base` (both evaluate results)."""
    eb, eo = base["episodes"], other["episodes"]
    if sorted(eb) != sorted(eo) or any(len(eb[t]) != len(eo[t]) for t in eb):
        only_b, only_o = sorted(set(eb) - set(eo)), sorted(set(eo) - set(eb))
        counts = sorted(t for t in set(eb) & set(eo) if len(eb[t]) != len(eo[t]))
        raise ValueError("the evaluations hold different tasks or episode counts: they are not paired"
                         + "".join(f"; {what}: {', '.join(ts[:4])}{' ...' if len(ts) > 4 else ''} ({len(ts)})"
                                   for what, ts in (("tasks only in the baseline", only_b),
                                                    ("tasks only in the other", only_o),
                                                    ("other episode counts", counts)) if ts)
                         + " (evaluations of disjoint tasks join with '+')")
    for which, ep in (("the baseline", eb), ("the other", eo)):
        missing = sum(r is None for recs in ep.values() for r in recs)
        if missing:
            raise ValueError(f"{which} has {missing} episodes not run yet (an interrupted run: rerun its command to "
                             "finish it, or compare with --ended_only on the episodes it has ended)")
    suite_of = {t: v["suite"] for t, v in base["summary"]["tasks"].items()}
    suites: dict[str, dict] = {}
    for task in base.get("settings", {}).get("tasks") or eb:  # the evaluation's order of tasks (and suites)
        s = suites.setdefault(suite_of[task], dict(episodes=0, base=0, other=0, base_only=0, other_only=0))
        for a, b in zip(eb[task], eo[task]):
            s["episodes"] += 1
            s["base"] += a["success"]
            s["other"] += b["success"]
            s["base_only"] += a["success"] and not b["success"]
            s["other_only"] += b["success"] and not a["success"]
    for s in suites.values():
        s["base_rate"], s["rate"] = s["base"] / s["episodes"], s["other"] / s["episodes"]
        s["diff_points"] = 100.0 * (s["rate"] - s["base_rate"])
    episodes = [e for t in eo for e in eo[t]]
    success_steps = {name: _success_steps(eps) for name, eps in (("base", eb), ("other", eo))}
    skipped = sum(e.get("decode", {}).get("skipped", 0.0) for e in episodes)
    return dict(
        label=label(other), suites=suites,
        mean_rate=float(np.mean([s["rate"] for s in suites.values()])),
        base_mean_rate=float(np.mean([s["base_rate"] for s in suites.values()])),
        worst_diff_points=min(s["diff_points"] for s in suites.values()),
        guard=all(s["diff_points"] >= -tolerance for s in suites.values()),
        **_per_episode(eo), **{f"base_{k}": v for k, v in _per_episode(eb).items()},
        success_steps=success_steps["other"], base_success_steps=success_steps["base"],
        skipped_share=skipped / sum(e["steps"] for e in episodes),
        base_only=sum(s["base_only"] for s in suites.values()),
        other_only=sum(s["other_only"] for s in suites.values()))


def _per_episode(episodes: dict) -> dict:
    """Mean steps and target passes per episode (passes None where a record has none): the
    passes are what an episode waits for, so their ratio to the baseline's is the saving a
    method makes per episode, its longer or shorter episodes included."""
    eps = [e for recs in episodes.values() for e in recs]
    passes = [e.get("decode", {}).get("target_passes") for e in eps]
    return dict(steps_per_episode=float(np.mean([e["steps"] for e in eps])),
                target_passes_per_episode=float(np.mean(passes)) if all(p is not None for p in passes) else None)


def _success_steps(episodes: dict) -> dict | None:
    """Mean and 90th percentile of the steps the successful episodes took (None: none succeeded)."""
    steps = [e["steps"] for eps in episodes.values() for e in eps if e["success"]]
    return dict(mean=float(np.mean(steps)), p90=float(np.percentile(steps, 90))) if steps else None


def _steps_text(s: dict | None) -> str:
    return "-" if s is None else f"{s['mean']:.0f} ({s['p90']:.0f})"


def table(base: dict, rows: list[dict], tolerance: float) -> str:
    suites = list(rows[0]["suites"]) if rows else []
    head = "| evaluation | " + " | ".join(suites) + " | mean | steps / ep | steps / success (p90) | " \
           f"passes / ep (baseline's / its) | skipped | base-only / other-only | within {tolerance:g} pts |"
    lines = [head, "|" + "---|" * (len(suites) + 8)]
    if rows:
        r0 = rows[0]
        base_passes = r0["base_target_passes_per_episode"]
        lines.append(f"| {label(base)} (baseline) | " + " | ".join(f"{100 * r0['suites'][s]['base_rate']:.1f}%"
                                                                   for s in suites)
                     + f" | {100 * r0['base_mean_rate']:.2f}% | {r0['base_steps_per_episode']:.1f} | "
                       f"{_steps_text(r0['base_success_steps'])} | {'-' if base_passes is None else f'{base_passes:.0f}'}"
                       " | | | |")
    for r in rows:
        cells = " | ".join(f"{100 * r['suites'][s]['rate']:.1f}% ({r['suites'][s]['diff_points']:+.1f})" for s in suites)
        passes, base_passes = r["target_passes_per_episode"], r["base_target_passes_per_episode"]
        passes = "-" if passes is None else f"{passes:.0f}" + (
            f" ({base_passes / passes:.2f}x)" if base_passes is not None and passes > 0 else "")
        lines.append(f"| {r['label']} | {cells} | {100 * r['mean_rate']:.2f}% | {r['steps_per_episode']:.1f} | "
                     f"{_steps_text(r['success_steps'])} | {passes} | {100 * r['skipped_share']:.0f}% | "
                     f"{r['base_only']} / {r['other_only']} | {'yes' if r['guard'] else 'no'} "
                     f"({r['worst_diff_points']:+.1f}) |")
    return "\n".join(lines)


def main(argv):
    if len(argv) < 3:
        raise app.UsageError("usage: python -m experiments.compare_evals BASELINE.json OTHER.json [OTHER.json ...] "
                             "(A.json+B.json: evaluations of disjoint tasks, joined)")
    if FLAGS.tolerance < 0:
        raise app.UsageError(f"--tolerance must be >= 0 points, got {FLAGS.tolerance}")
    try:
        base, others = load(argv[1]), [load(p) for p in argv[2:]]
        if FLAGS.common_tasks:
            (base, *others), left_out = common([base, *others])
            if not base["episodes"]:
                raise ValueError("the evaluations hold no task in common")
            if left_out:
                print(f"left out ({len(left_out)} tasks not in every evaluation): {', '.join(left_out)}")
        if FLAGS.ended_only:
            (base, *others), unended = ended([base, *others])
            if not base["episodes"]:
                raise ValueError("no episode has ended in every evaluation")
            if unended:
                print(f"left out: {unended} of the baseline's episodes not ended in every evaluation "
                      "(the rates below lean high: the unended episodes are the slow ones)")
        rows = [compare(base, o, FLAGS.tolerance) for o in others]
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    print(table(base, rows, FLAGS.tolerance))


if __name__ == "__main__":
    cli.run(main)
