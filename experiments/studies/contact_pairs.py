"""What `PhysicsConfig.max_geom_pairs` must keep: for each of MJX's collision functions (box-box,
box-mesh, ...), how far down a touching geom pair ranks when the pairs are ordered as MJX's
broad phase orders them, by the gap between their bounding spheres.

  python -m experiments.studies.contact_pairs --suites=all --episodes=4 --out=results/contact_pairs.json

Runs the scripted expert on --episodes evaluation states of every task of --suites, every
contact and every pair simulated (`max_contacts=0,max_geom_pairs=0`, the rest of the physics
defaults), and after every control step ranks each collision function's pairs per env. A pair
touches when one of its contact slots has a negative distance. `max_geom_pairs=N` keeps every
touching pair of these episodes when N is at least the largest rank printed; `max_contacts=N`
keeps every active contact when N is at least the most active contacts of one env at one step.
"""

from __future__ import annotations


from absl import flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import numpy as np

from envs import expert, physics, rollout, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from experiments import cli
from heisd_jax import results_io

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "all", f"Suites of {list(tasks_lib.SUITES)} or 'all'.")
flags.DEFINE_integer("episodes", 4, "Evaluation states per task.", lower_bound=1)
flags.DEFINE_integer("max_steps", 420, "Control steps at most (every episode ends by the longest task's limit).",
                     lower_bound=1)
flags.DEFINE_string("out", "", "Optional JSON output path.")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    task_list = cli.task_list(FLAGS.suites)
    cfg = physics.PhysicsConfig(max_contacts=0, max_geom_pairs=0)
    env = TabletopEnv(task_list, EnvConfig(render=False, physics=cfg))
    groups = physics.collision_groups(env.mj_model)
    n = len(task_list) * FLAGS.episodes
    tids, keys = env.cycling_eval_starts(n)
    states = rollout.host_loop(env, expert.policy(env), keys, tids)
    next(states)  # the reset state; contact slots hold their pairs from the first step on
    state = next(states)
    # Contact slot -> (its pair's index within its group); the slots' pairs are fixed without culling.
    slot_geom = np.asarray(state.data._impl.contact.geom)[0]
    slot_of = {name: [np.flatnonzero((slot_geom == p).all(-1)) for p in pairs] for name, pairs in groups.items()}
    worst = {name: 0 for name in groups}
    hist = {name: np.zeros(len(pairs) + 1, np.int64) for name, pairs in groups.items()}
    rbound = env.mj_model.geom_rbound
    most_active = 0
    for t in range(FLAGS.max_steps):
        live = ~np.asarray(state.done)
        xpos = np.asarray(state.data.geom_xpos)
        dist = np.asarray(state.data._impl.contact.dist)
        most_active = max(most_active, int(((dist < 0) & live[:, None]).sum(-1).max()))
        for name, pairs in groups.items():
            touching = np.stack([(dist[:, s] < 0).any(-1) for s in slot_of[name]], -1) & live[:, None]  # [B, P]
            ranks = physics.broad_phase_ranks(xpos, rbound, pairs)[touching]
            np.add.at(hist[name], ranks, 1)
            worst[name] = max(worst[name], int(ranks.max(initial=0)))
        if not live.any():
            break
        state = next(states)
    success = float(np.asarray(state.success).mean())
    print(f"{n} expert episodes ({FLAGS.episodes} per task), {t + 1} control steps, success {success:.3f}; "
          f"most active contacts of one env at one step: {most_active}")
    print(f"{'collision function':<20}{'pairs':>6}{'largest rank touching':>23}")
    for name, pairs in groups.items():
        print(f"{name:<20}{len(pairs):>6}{worst[name] or '-':>23}")
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {
            **results_io.provenance(cli.command_line()), "episodes": n, "success": success,
            "most_active_contacts": most_active,
            "groups": {name: {"pairs": len(pairs), "largest_touching_rank": worst[name],
                              "touching_rank_counts": hist[name][1:].tolist()} for name, pairs in groups.items()}})


if __name__ == "__main__":
    cli.run(main)
