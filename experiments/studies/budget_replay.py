"""The automatic draft budget replayed on measured acceptance, priced by a measured cost table.

With strict drafter trees after the relaxed candidates (heisd's default), every budget option
executes the same action on a step (the candidates' accepted prefix, then the target's greedy
tokens), so one step's draft rounds under each option can be measured by replaying each option
alone (`budget=fixed`) on the same recorded states, and the chooser of `heisd_jax.budget` then
run over those per-step rounds (`budget.simulate_recorded`) without running a model again:
what it would choose, and what
that costs by a cost table from another device or scale (the 7B expansion's on an H200, say),
against each fixed option and against an oracle that knows every step's rounds.

  python -m experiments.studies.budget_replay --suites=all --steps=30 --lane_envs=8 \\
      --tables=experiments/results/costs/7b_bf16_h200/costs_4d1af0212330f457.json --out=R.json

On a GPU, `--settings=target_scale=llama2-7b,dtype=bfloat16` replays the options with the 7B
expansion in bf16, so the rounds are those a 7B benchmark there needs (bf16 picks other tokens
than the CPU's float32 on many states), on states recorded as bench_methods records them (the
shipped target's AR).

Per step of the batch-1 replay it records: skipped (no target pass), the mode (retrieval or
drafter) and the rounds of `ar+retrieval` (`continuation=ar`: single-token passes) and of each
tree (after the candidates on retrieval steps, from the prefill on drafter steps). A tree
without the candidates on a retrieval step, and plain AR on one (no query, so no skip and
another action), are priced from the table but change no later step: the replay cannot say
what they would have executed. Skipped steps cost nothing here. Each figure comes with the 5-95 %
range of x AR over the replayed envs resampled (`replay.env_interval`): a replay of few envs, like a
GPU benchmark's, moves with the episodes it draws.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA flags before JAX starts)
from envs import language, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from experiments import cli
from heisd_jax import budget, checkpoint, cost_model, results_io
from heisd_jax.harness import methods, replay

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "all", f"Suites of {list(tasks_lib.SUITES)} or 'all'.")
flags.DEFINE_integer("steps", 30, "Recorded control steps per env.")
flags.DEFINE_integer("record_envs", 64, "Recorded envs.")
flags.DEFINE_integer("lane_envs", 8, "Recorded envs the batch-1 replay plays one after another.")
flags.DEFINE_string("trees", "4x2x8/8x4x32", "Draft trees replayed (TOPKxDEPTHxTOTAL separated by '/').")
flags.DEFINE_list("horizons", ["0", "60"], "Steps after which the chooser starts afresh (0: never): a short "
                  "benchmark replay (bench_methods' 60 steps per lane) pays its first tries over fewer steps.")
flags.DEFINE_list("tables", [], "Cost-table JSON files (cost_model.CostTable) to price the choices by.")
flags.DEFINE_string("out", "", "JSON output path (with every step's rounds, for --rounds_from).")
flags.DEFINE_integer("jitter", 0, "Per automatic row, also replay the chooser this many times on the cost table with "
                     "every entry scaled by 1 + --jitter_sd x N(0, 1) (one seed each), priced by the table as "
                     "measured: how much the choice, and its figure, move with the table's error.")
flags.DEFINE_float("jitter_sd", 0.01, "Relative standard deviation of --jitter's perturbation.")
flags.DEFINE_string("rounds_from", "", "Instead of replaying: the per-step rounds of an earlier --out file.")
flags.DEFINE_string("settings", "", "heisd settings every replayed option runs with, key=value,... (e.g. "
                    "target_scale=llama2-7b,dtype=bfloat16: the rounds of the 7B expansion on this device); the "
                    "recording stays the shipped target's AR, as in bench_methods. Not the options' own settings "
                    "(budget, continuation, top_k, depth, total_tokens).")
cli.define_paths("checkpoint", "drafter", "datastore")


def option_settings(trees) -> dict[str, dict]:
    """Each replayed option's own heisd settings: continuation=ar after the candidates, then each tree."""
    runs = {"ar+retrieval": {"budget": "fixed", "continuation": "ar"}}
    runs.update({"x".join(map(str, t)): {"budget": "fixed", "top_k": t[0], "depth": t[1], "total_tokens": t[2]}
                 for t in trees})
    return runs


def replay_settings(text: str, trees) -> dict:
    """--settings, checked as heisd's with every option's own (ValueError naming the problem)."""
    given = dict(kv.split("=", 1) for kv in text.split(",") if kv)
    own = sorted(set(given) & {k for extra in option_settings(trees).values() for k in extra})
    if own:
        raise ValueError(f"--settings: {own} are set by each replayed option; give the others "
                         "(target_scale, dtype, patchify, acceptance, ...)")
    for extra in option_settings(trees).values():
        methods.check_settings("heisd", {**given, **{k: str(v) for k, v in extra.items()}})
    return methods.check_settings("heisd", given)


def per_step_rounds(env, states, running, trees, settings: dict):
    """{'skipped', 'drafter', 'ar+retrieval', tree name...}: per replayed step at batch 1 (each
    option with `settings` besides its own), and the share of steps whose action equals
    continuation=ar's under every tree."""
    t_idx, e_idx = rollout.replay_lanes(running, min(FLAGS.record_envs, FLAGS.lane_envs), 1)
    sub = jax.tree.map(lambda x: x[t_idx, e_idx], states)
    out, actions = {"env": e_idx[:, 0]}, {}
    for name, extra in option_settings(trees).items():
        policy = methods.make_policy("heisd", env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                     datastore=FLAGS.datastore, batch_size=1, **settings, **extra)
        acts, stats = jax.device_get(replay.replay_fn(policy)(policy.params, sub))
        actions[name] = np.asarray(acts)[:, 0]
        out[name] = np.asarray(stats["rounds"])[:, 0]
        out.setdefault("skipped", np.asarray(stats["skipped"])[:, 0] > 0)
        out.setdefault("drafter", np.asarray(stats["drafter_mode"])[:, 0] > 0)
        print(f"{name}: {out[name].mean():.2f} rounds per step", flush=True)
    ref = actions["ar+retrieval"]
    same = float(np.mean([np.all(a == ref, -1).mean() for a in actions.values()]))
    return out, same


def fixed_ms(costs, opts, rounds, tree: str | None) -> np.ndarray:
    """The priced ms per step of one fixed option (0 on skipped steps): a tree (with the
    candidates on retrieval steps) or, for None, continuation=ar."""
    fixed, per_round, names = np.asarray(costs.fixed_ms), np.asarray(costs.round_ms), [o.name for o in opts]
    spent = np.zeros(len(rounds["skipped"]))
    for t in range(len(rounds["skipped"])):
        if rounds["skipped"][t]:
            continue
        base = "ar" if tree is None else tree
        name = base if rounds["drafter"][t] else base + "+retrieval"
        if tree is None and rounds["drafter"][t]:
            spent[t] = fixed[0]  # AR from the prefill: the whole AR decode
            continue
        i = names.index(name)
        spent[t] = fixed[i] + rounds["ar+retrieval" if tree is None else tree][t] * per_round[i]
    return spent


def jittered(cfg, costs, opts, rounds, horizon, ar_total) -> dict:
    """x AR of the chooser fed --jitter perturbed copies of `costs` (each entry scaled by
    1 + jitter_sd x N(0, 1), seeds 0, 1, ...), each priced by `costs` itself."""
    xs = []
    for seed in range(FLAGS.jitter):
        rng = np.random.default_rng(seed)
        noisy = budget.Costs(*(np.asarray(a * (1 + FLAGS.jitter_sd * rng.standard_normal(a.shape)), np.float32)
                               for a in (np.asarray(costs.fixed_ms), np.asarray(costs.round_ms))))
        ms, _ = budget.simulate_recorded(cfg, noisy, opts, rounds, horizon, prices=costs)
        xs.append(float(ar_total / ms.sum()))
    return {"mean": float(np.mean(xs)), "min": min(xs), "max": max(xs), "n": len(xs), "sd": FLAGS.jitter_sd}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        trees = budget.parse_trees(FLAGS.trees)
        task_list = tasks_lib.get_tasks(FLAGS.suites)
        horizons = [int(h) for h in FLAGS.horizons]
        if any(h < 0 for h in horizons):
            raise ValueError(f"--horizons must be >= 0, got {horizons}")
        if FLAGS.jitter < 0 or not 0 < FLAGS.jitter_sd < 0.5:
            raise ValueError(f"need --jitter >= 0 and 0 < --jitter_sd < 0.5, got {FLAGS.jitter}, {FLAGS.jitter_sd}")
        settings = replay_settings(FLAGS.settings, trees)
        if settings and FLAGS.rounds_from:
            raise ValueError("--settings apply to a replay; --rounds_from reads one (its settings are in its file)")
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if not FLAGS.tables:
        raise app.UsageError("--tables: give at least one cost-table JSON file")
    tables = []
    for path in FLAGS.tables:
        table = cost_model.CostTable(**json.loads(Path(path).read_text()))
        missing = {"x".join(map(str, t)) for t in trees} - set(table.options)
        if missing or table.options[0] != "ar":
            raise app.UsageError(f"{path}: options {table.options} lack {sorted(missing) or 'ar first'}")
        if table.key.get("batch") != 1:
            raise app.UsageError(f"{path} prices batch {table.key.get('batch')}: the replay is at batch 1 (a larger "
                                 f"batch pays its slowest row's rounds), so give batch-1 tables")
        tables.append((path, table))
    if FLAGS.rounds_from:
        before = results_io.read_json(FLAGS.rounds_from)
        rounds = {k: np.asarray(v) for k, v in before["per_step"].items()}
        missing = {"x".join(map(str, t)) for t in trees} - set(rounds)
        if missing:
            raise app.UsageError(f"--rounds_from={FLAGS.rounds_from} has no rounds of {sorted(missing)}")
        same, settings = before["same_action_share"], before.get("settings", {})
    else:
        checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)  # fails early on a bad checkpoint
        env = TabletopEnv(task_list, methods.env_config("ar", FLAGS.checkpoint))
        states, _, done = replay.record(env, methods.make_policy("ar", env, checkpoint=FLAGS.checkpoint),
                                        FLAGS.record_envs, FLAGS.steps)
        rounds, same = per_step_rounds(env, states, ~np.asarray(done), trees, settings)
    n = len(rounds["skipped"])
    print(f"{n} steps, skipped {rounds['skipped'].mean():.2f}, drafter mode {rounds['drafter'].mean():.2f}; "
          f"actions equal to continuation=ar's under every option: {same:.3f}")
    report = {**results_io.provenance(cli.command_line()), "steps": n, "same_action_share": same, "settings": settings,
              "skipped": float(rounds["skipped"].mean()), "drafter_mode": float(rounds["drafter"].mean()),
              "mean_rounds": {k: float(np.mean(v)) for k, v in rounds.items() if k not in ("skipped", "drafter", "env")},
              "tables": {}, "per_step": {k: np.asarray(v).tolist() for k, v in rounds.items()}}
    for path, table in tables:
        all_opts = tuple(budget.Option(None if n_.removesuffix("+retrieval") == "ar" else
                                       budget.parse_trees(n_.removesuffix("+retrieval"))[0], n_.endswith("+retrieval"))
                         for n_ in table.options)
        costs = table.costs()
        ar_ms = float(table.fixed_ms[0])
        ar_total = ar_ms * n
        rows = {}

        def priced(ms, **extra):  # x AR, and its spread over the envs where the steps name them
            out = {"x_ar": float(ar_total / ms.sum()), **extra}
            if "env" in rounds:
                out["x_ar_env_90"] = replay.env_interval(ms, ar_ms, rounds["env"])
            return out
        per_option = {name: fixed_ms(costs, all_opts, rounds, None if name == "ar+retrieval" else name)
                      for name in ["ar+retrieval"] + ["x".join(map(str, t)) for t in trees]}
        for name, ms in per_option.items():
            rows[f"fixed {name}"] = priced(ms)
        sets = [trees] + ([(t,) for t in trees] if len(trees) > 1 else [])
        for tree_set in sets:
            keep = [i for i, o in enumerate(all_opts) if o.tree is None or o.tree in tree_set]
            opts = tuple(all_opts[i] for i in keep)
            sub = budget.Costs(fixed_ms=costs.fixed_ms[np.asarray(keep)], round_ms=costs.round_ms[np.asarray(keep)])
            cfg = dataclasses.replace(budget.BudgetConfig(), trees=tree_set)
            for horizon in horizons:
                ms, chosen = budget.simulate_recorded(cfg, sub, opts, rounds, horizon)
                label = "auto " + "/".join("x".join(map(str, t)) for t in tree_set) + (
                    f", afresh every {horizon} steps" if horizon else "")
                rows[label] = priced(ms, chosen={k: v / n for k, v in chosen.items() if v})
                if FLAGS.jitter:
                    rows[label]["x_ar_jittered"] = jittered(cfg, sub, opts, rounds, horizon, ar_total)
        # the oracle: per step the cheapest option that ran on it (retrieval steps: ar+retrieval or a
        # tree after the candidates; drafter steps: AR or a tree from the prefill), as the fixed options price it
        best = np.minimum.reduce([np.where(rounds["skipped"], 0.0, ar_ms), *per_option.values()])
        rows["oracle per step"] = priced(best)
        print(f"{path} ({table.key.get('device')}, batch {table.key.get('batch')}): AR {table.fixed_ms[0]:.2f} ms")
        for label, row in rows.items():
            chosen = " ".join(f"{k} {v:.2f}" for k, v in row.get("chosen", {}).items())
            spread = "[{:.2f}..{:.2f}] over envs".format(*row["x_ar_env_90"]) if "x_ar_env_90" in row else ""
            if "x_ar_jittered" in row:
                spread += " {mean:.2f} [{min:.2f}..{max:.2f}] over {n} tables jittered".format(**row["x_ar_jittered"])
            print(f"  {label:<24} {row['x_ar']:.2f}x AR {spread} {chosen}")
        report["tables"][path] = rows
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, report)


if __name__ == "__main__":
    cli.run(main)
