"""Collects scripted-expert demonstrations, batched, into an envs.demos dataset.

  python -m experiments.collect_demos --suites=all --episodes_per_task=50 --num_envs=256 \
      --out=data/demos

Episodes use the training initial-state keys (disjoint from the 50 evaluation states).
Only successful episodes are kept; the dataset appears at --out only once complete.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

import envs  # noqa: F401  (XLA CPU flag before JAX starts)
from envs import camera, demos, expert, rollout, scene, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names.")
flags.DEFINE_integer("episodes_per_task", 50, "Training episodes attempted per task.")
flags.DEFINE_integer("num_envs", 64, "Episodes run in parallel.")
flags.DEFINE_integer("image_size", 64, "Camera resolution (square).")
flags.DEFINE_float("action_noise", 0.1, "Std of Gaussian noise added to the executed motion actions (diversity); "
                   "the recorded labels are the expert's clean actions.")
flags.DEFINE_integer("first_episode", 0, "Index of the first training initial state (to extend a dataset).")
flags.DEFINE_string("out", "data/demos", "Output dataset directory.")
flags.DEFINE_bool("overwrite", False, "Replace an existing dataset at --out (only once the new one is complete).")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    task_list = tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
    for name in ("episodes_per_task", "num_envs", "image_size"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1")
    cam = camera.CameraConfig(height=FLAGS.image_size, width=FLAGS.image_size)
    env = TabletopEnv(task_list, EnvConfig(camera=cam))
    policy = expert.policy(env)
    meta = dict(
        suites=sorted({t.suite for t in task_list}),
        tasks=[{"name": t.name, "suite": t.suite, "instruction": t.instruction} for t in task_list],
        image_size=FLAGS.image_size, control_dt=scene.CONTROL_DT, executed_action_noise=FLAGS.action_noise,
        labels="clean expert actions",
        split="train",
    )
    writer = demos.DatasetWriter(FLAGS.out, meta, overwrite=FLAGS.overwrite)
    pairs = [(t, FLAGS.first_episode + e) for t in range(len(task_list)) for e in range(FLAGS.episodes_per_task)]
    n_steps = int(max(t.max_steps for t in task_list))
    record = jax.jit(lambda k, t: rollout.record_episodes(env, policy, k, t, n_steps, exec_noise=FLAGS.action_noise))
    kept = 0
    try:
        with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} episodes"),
                      TextColumn("kept {task.fields[kept]}"), TimeRemainingColumn()) as bar:
            job = bar.add_task("collecting", total=len(pairs), kept=0)
            for start in range(0, len(pairs), FLAGS.num_envs):
                chunk = pairs[start: start + FLAGS.num_envs]
                pad = chunk + [chunk[-1]] * (FLAGS.num_envs - len(chunk))
                tids, eps = np.array(pad).T
                keys = env.initial_state_keys(tids, eps, split="train")
                final, traj = jax.device_get(record(keys, jnp.asarray(tids, jnp.int32)))
                steps, records, row = {f: [] for f in demos.STEP_FIELDS}, [], 0
                for i, (t, e) in enumerate(chunk):
                    if not final.success[i]:
                        continue
                    n = int(final.step[i])
                    for f in demos.STEP_FIELDS:
                        steps[f].append(traj[f][:n, i])
                    task = task_list[t]
                    records.append(dict(task=task.name, suite=task.suite, task_index=t, instruction=task.instruction,
                                        episode=int(e), start=row, length=n))
                    row += n
                if records:
                    writer.add_shard({f: np.concatenate(v) for f, v in steps.items()}, records)
                kept += len(records)
                bar.update(job, advance=len(chunk), kept=kept)
        path = writer.finalize()
    except BaseException:
        writer.abort()
        raise
    print(f"kept {kept}/{len(pairs)} successful episodes ({kept / len(pairs):.1%}) -> {path}")


if __name__ == "__main__":
    app.run(main)
