"""Which geoms each camera view ever shows: the scripted expert's episodes of every task, the
target's views rendered every --every control steps, and per view and geom the share of
those states in which some pixel shows the geom. Geoms a view never shows are what a
ray-cast scene of only what that view can see would leave out (issue: the camera's share).

  python -m experiments.studies.camera_visibility --envs=40 --steps=200 --every=20 [--out=camera_visibility_cpu.json]
"""

from __future__ import annotations

import itertools

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import mujoco
import numpy as np

from envs import camera, expert, rollout
from envs.env import TabletopEnv
from experiments import cli
from heisd_jax import results_io
from heisd_jax.harness import methods

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "all", "Suites whose tasks the envs cycle over.")
flags.DEFINE_integer("envs", 40, "Parallel envs (cycling over the tasks, then their initial states).", lower_bound=1)
flags.DEFINE_integer("steps", 200, "Control steps of each env's episode to sample.", lower_bound=1)
flags.DEFINE_integer("every", 20, "Sample every this many control steps.", lower_bound=1)
flags.DEFINE_string("out", "", "Optional JSON output path.")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    env = TabletopEnv(cli.task_list(FLAGS.suites), methods.env_config("ar"))  # the target's views
    mj, cfg = env.mj_model, env.config.camera
    tids, keys = env.cycling_eval_starts(FLAGS.envs)
    seen = jax.jit(jax.vmap(lambda d: camera.view_geoms(mj, env.model, d, cfg)))
    counts, states = np.zeros((len(cfg.views), mj.ngeom), np.int64), 0
    for t, state in enumerate(itertools.islice(rollout.host_loop(env, expert.policy(env), keys, tids), FLAGS.steps)):
        if t % FLAGS.every == 0:
            counts += np.asarray(seen(state.data)).sum(0)
            states += FLAGS.envs
    names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_GEOM, g) or f"{mj.body(mj.geom_bodyid[g]).name}/{g}"
             for g in range(mj.ngeom)]
    views = {v: {names[g]: float(counts[i, g] / states) for g in range(mj.ngeom)} for i, v in enumerate(cfg.views)}
    for v, share in views.items():
        print(f"{v}: {sum(s > 0 for s in share.values())} of {mj.ngeom} geoms shown in some of {states} states; "
              f"never: {', '.join(n for n, s in share.items() if s == 0) or 'none'}")
        print("  " + ", ".join(f"{n} {s:.0%}" for n, s in share.items() if s > 0))
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "states": states,
                                                 "share_of_states_shown": views})


if __name__ == "__main__":
    cli.run(main)
