"""What re-trying losing options costs the automatic budget, by the arithmetic of a measured
cost table (no model runs): every speculative option is assumed to need --rounds draft rounds
(for ar+retrieval: single-token passes) and to cost what the table predicts for them; AR
costs its measured decode.

  python -m experiments.studies.budget_sim --tables=experiments/results/costs/cost_table_prev_target_b256_h200.json \
      --steps=40,420 --rounds=6

Prints, per table and number of steps, the time over always running AR for the chooser of
`heisd_jax.budget` (bounded-cost retries) and for the policy it replaced ("drift": unchosen
estimates moved 1% per step back to their optimistic prior, re-trying every losing option
every ~100 steps).
"""

from __future__ import annotations

import json

import numpy as np
from absl import app, flags

from heisd_jax import budget, cost_model
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_list("tables", [], "Cost-table JSON files (cost_model.CostTable, as cached by calibration).")
flags.DEFINE_list("steps", ["40", "420"], "Control steps simulated.")
flags.DEFINE_float("rounds", 6.0, "Draft rounds every speculative option needs (the batch's largest).")
flags.DEFINE_float("retry_share", budget.BudgetConfig.retry_share, "BudgetConfig.retry_share.")


def option(name: str) -> budget.Option:
    """'ar' | 'ar+retrieval' | 'KxDxN' | 'KxDxN+retrieval' -> budget.Option."""
    tree = name.removesuffix("+retrieval")
    return budget.Option(None if tree == "ar" else budget.parse_trees(tree)[0], name != tree)


def drift(costs: budget.Costs, opts, true_rounds: np.ndarray, steps: int) -> float:
    """Total ms of the former policy (decay 0.1, unchosen estimates drift 1% per step to the prior)."""
    fixed, rnd = np.asarray(costs.fixed_ms), np.asarray(costs.round_ms)
    prior = np.asarray([o.prior_rounds for o in opts])
    est, runs, spent = prior.copy(), np.zeros(len(opts)), 0.0
    for _ in range(steps):
        o = int(np.argmin(fixed + est * rnd))
        spent += fixed[o] + true_rounds[o] * rnd[o]
        hit = np.arange(len(opts)) == o
        ran = np.where(runs == 0, true_rounds, 0.9 * est + 0.1 * true_rounds)
        est, runs = np.where(hit, ran, est + 0.01 * (prior - est)), runs + hit
    return spent


def main(argv):
    del argv
    if not FLAGS.tables:
        raise app.UsageError("--tables: give at least one cost-table JSON file")
    try:
        steps = [int(s) for s in FLAGS.steps]
        cfg = budget.BudgetConfig(mode="auto", retry_share=FLAGS.retry_share)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    for path in FLAGS.tables:
        table = cost_model.CostTable(**json.loads(open(path).read()))
        opts = tuple(option(n) for n in table.options)
        if opts[0].tree is not None:
            raise app.UsageError(f"{path}: the first option must be 'ar', got {table.options}")
        costs = table.costs()
        true_rounds = np.asarray([0.0 if o == budget.Option(None) else FLAGS.rounds for o in opts])
        ar_ms = float(costs.fixed_ms[0])
        print(f"{path}: {table.key.get('device')} batch {table.key.get('batch')}, AR {ar_ms:.2f} ms")
        for n in steps:
            runs, spent = budget.simulate(cfg, costs, opts, true_rounds, n)
            old = drift(costs, opts, true_rounds, n)
            print(f"  {n} steps: time / AR's  retries {spent / (n * ar_ms):.4f}  drift {old / (n * ar_ms):.4f}"
                  f"  (retries ran {dict(zip(table.options, runs.astype(int).tolist()))})")


if __name__ == "__main__":
    cli.run(main)
