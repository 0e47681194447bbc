"""How many iterations MJX's constraint solver takes under the scripted expert, per solver
tolerance: what `PhysicsConfig.tolerance` and `solver_iterations` trade.

  python -m experiments.studies.solver_iterations --suites=all --episodes=2 --every=5 --out=results/solver_iterations.json

Runs the expert on --episodes evaluation states of every task of --suites under the default
physics, keeps the state of every live env every --every control steps, and counts on each
state the iterations of the solve MJX would run next (`envs.physics.solver_iterations`) under
each of --tolerances. Batched, MJX's solver loop runs until every env has converged, so besides
each state's count it prints the mean over sampled steps of the most any live env needed (the
loop's trip count for this batch), and the share of states a cap of k iterations would cut short.
"""

from __future__ import annotations

import dataclasses

from absl import flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import numpy as np

from envs import expert, physics, rollout, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from experiments import cli
from heisd_jax import results_io

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "all", f"Suites of {list(tasks_lib.SUITES)} or 'all'.")
flags.DEFINE_integer("episodes", 2, "Evaluation states per task.", lower_bound=1)
flags.DEFINE_integer("max_steps", 150, "Control steps of the rollout.", lower_bound=1)
flags.DEFINE_integer("every", 5, "Control steps between sampled states.", lower_bound=1)
flags.DEFINE_list("tolerances", ["1e-8", "1e-6", "1e-5", "1e-4"], "Solver tolerances to count under.")
flags.register_validator("tolerances", lambda v: all(_is_tolerance(x) for x in v),
                         "--tolerances takes non-negative numbers, e.g. 1e-8,1e-5")
cli.define_physics_flag()
flags.DEFINE_string("out", "", "Optional JSON output path.")


def _is_tolerance(text: str) -> bool:
    try:
        return float(text) >= 0
    except ValueError:
        return False


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    task_list = cli.task_list(FLAGS.suites)
    cfg = cli.physics_config()
    env = TabletopEnv(task_list, EnvConfig(render=False, physics=cfg))
    n = len(task_list) * FLAGS.episodes
    tids, keys = env.cycling_eval_starts(n)
    states = rollout.host_loop(env, expert.policy(env), keys, tids)
    samples, live = [], []
    for t, state in zip(range(FLAGS.max_steps), states):
        if t % FLAGS.every == 0:
            samples.append(state.data)
            live.append(~np.asarray(state.done))
    live = np.stack(live)  # [T, B]
    rows = []
    print(f"{n} expert episodes, {live.sum()} live states ({len(samples)} sampled steps); physics: "
          f"{physics.describe(cfg) or 'defaults'}")
    print(f"{'tolerance':>10}  {'mean':>5}  {'batch max':>9}  {'> k iterations, k = 1..5':<34}  histogram (0, 1, 2, ...)")
    for text in FLAGS.tolerances:
        tcfg = dataclasses.replace(cfg, tolerance=float(text))
        m = TabletopEnv(task_list, EnvConfig(render=False, physics=tcfg)).model
        count = jax.jit(jax.vmap(lambda d: physics.solver_iterations(m, d, tcfg)))
        its = np.stack([np.asarray(count(d)) for d in samples])  # [T, B]
        on = its[live]
        hist = np.bincount(on, minlength=tcfg.solver_iterations + 1)
        batch_max = float(np.where(live, its, 0).max(1)[live.any(1)].mean())
        over = [float((on > k).mean()) for k in range(1, 6)]
        rows.append({"tolerance": float(text), "mean": float(on.mean()), "batch_max_mean": batch_max,
                     "share_over_k": over, "histogram": hist.tolist()})
        print(f"{float(text):>10g}  {on.mean():>5.2f}  {batch_max:>9.2f}  {' '.join(f'{x:.3f}' for x in over):<34}  "
              f"{hist.tolist()}", flush=True)
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "episodes": n,
                                                 "physics": dataclasses.asdict(cfg), "states": int(live.sum()),
                                                 "rows": rows})


if __name__ == "__main__":
    cli.run(main)
