"""One episode's timeline: end-effector speed, the kinematic metric and the decoding mode
HeiSD chose at every control step (retrieval verified, retrieval skipped, drafter).

  python -m experiments.studies.timeline --task=pick_red_block --method=heisd \
      --settings=top_k=4,depth=2,total_tokens=8 --out=results/timeline.png

Runs the episode (fixed evaluation initial state --episode of --task) in closed loop with
the method's policy, recording per step the MJX end-effector velocity and the policy's
statistics, and plots them (matplotlib) with the target passes per step; also writes the
per-step numbers next to the plot (.json).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from envs import rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax.harness import methods
from experiments import cli

FLAGS = flags.FLAGS
cli.define_cost_flags()
flags.DEFINE_string("task", "pick_red_block", "Task name.")
flags.DEFINE_integer("episode", 0, "Evaluation initial state (0..49).")
flags.DEFINE_enum("method", "heisd", ["retrieval", "heisd"], "Hybrid method.")
flags.DEFINE_string("settings", "", "The method's settings, key=value,key=value.")
flags.DEFINE_integer("steps", 0, "Control steps (default: the task's limit).")
cli.define_paths("checkpoint", "drafter", "datastore")
flags.DEFINE_string("out", "results/timeline.png", "PNG path (the numbers go to the same name, .json).")

MODES = (("retrieval_verified", "retrieval, verified", "tab:blue"), ("skipped", "retrieval, skipped", "tab:green"),
         ("drafter_mode", "drafter", "tab:orange"))


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        settings = methods.check_settings(FLAGS.method, dict(kv.split("=", 1) for kv in FLAGS.settings.split(",") if kv))
        task = tasks_lib.get_tasks("all", [FLAGS.task])
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if not 0 <= FLAGS.episode < tasks_lib.N_EVAL_INIT_STATES:
        raise app.UsageError(f"--episode must be in 0..{tasks_lib.N_EVAL_INIT_STATES - 1}")
    env = TabletopEnv(task, methods.env_config(FLAGS.method, FLAGS.checkpoint))
    policy = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                 datastore=FLAGS.datastore, batch_size=1,
                                 **cli.cost_kwargs(), **settings)
    n = FLAGS.steps or task[0].max_steps
    keys = env.initial_state_keys(np.array([0]), np.array([FLAGS.episode]))
    final, traj = jax.device_get(jax.jit(lambda p, k: rollout.record_episodes(
        env, dataclasses.replace(policy, params=p), k, jnp.zeros((1,), jnp.int32), n))(policy.params, keys))
    running = ~np.asarray(traj["done"][:, 0])
    t = np.flatnonzero(running)
    speed = np.linalg.norm(traj["ee_vel"][:, 0], axis=-1)[t]
    stats = {k: np.asarray(v[:, 0])[t] for k, v in traj["stats"].items()}
    record = {"task": FLAGS.task, "episode": FLAGS.episode, "method": FLAGS.method, "settings": settings,
              "success": bool(final.success[0]), "steps": int(len(t)), "ee_speed": speed.tolist(),
              **{k: v.tolist() for k, v in stats.items()}}
    out = Path(FLAGS.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(record))
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.plot(t, speed, c="k", lw=1.2, label="end-effector speed (m/s)")
    top = max(float(speed.max()), 1e-3) * 1.1
    for key, label, colour in MODES:
        on = stats[key] > 0
        ax.fill_between(t, 0, top, where=on, color=colour, alpha=0.18, step="mid", label=label, lw=0)
    axm = ax.twinx()
    axm.plot(t, stats["metric"], c="tab:red", lw=0.8, alpha=0.7)
    axm.set_ylabel("fused metric M", color="tab:red")
    ax.set_ylim(0, top)
    ax.set_ylabel("speed (m/s)")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(f"{FLAGS.method} on {FLAGS.task} #{FLAGS.episode}: {'success' if record['success'] else 'failure'}, "
                 f"{stats['target_passes'].mean():.2f} target passes/action", fontsize=9)
    ax2.bar(t, stats["target_passes"], width=1.0, color="gray")
    ax2.set_ylabel("target\npasses")
    ax2.set_xlabel("control step")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"{len(t)} steps, success {record['success']}, target passes/action {stats['target_passes'].mean():.2f}, "
          f"modes: " + ", ".join(f"{label} {stats[k].mean():.2f}" for k, label, _ in MODES) + f" -> {out}")


if __name__ == "__main__":
    cli.run(main)
