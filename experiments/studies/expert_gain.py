"""The scripted expert at several rotation gains: success, steps per success and how its yaw
labels are spread (saturated, zero, in between), per suite.

  python -m experiments.studies.expert_gain --gains=1.2,0.6,0.4 --episodes=4 --out=results/expert_gain.json

Runs `envs.expert` (`ExpertConfig(rot_gain=G)`) on --episodes training initial states of every
task of --suites in one batch, without rendering, its executed actions noised as the
demonstrations' are (--action_noise), its labels clean. A gain above 1 turns more than the
rotation error each step (bounded by the step's limit), so the yaw label saturates more often:
the share printed as `yaw_saturated` (|a| > 0.99). docs/target.md reads the figures.
"""

from __future__ import annotations

import time

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from envs import expert, rollout
from envs.env import EnvConfig, TabletopEnv
from experiments import cli
from heisd_jax import results_io

FLAGS = flags.FLAGS
flags.DEFINE_list("gains", ["1.2", "0.6", "0.4"], "Rotation gains to run (each > 0).")
flags.DEFINE_string("suites", "all", "Suites, or 'all'.")
flags.DEFINE_integer("episodes", 4, "Training initial states per task.", lower_bound=1)
flags.DEFINE_float("action_noise", 0.15, "Std of the noise on the executed motion dimensions (labels clean).",
                   lower_bound=0.0)
flags.DEFINE_string("out", "", "Optional JSON output path.")


def label_spread(yaw: np.ndarray) -> dict:
    """Shares of yaw labels (in [-1, 1]) that are saturated (|a| > 0.99), zero (|a| < 1/128,
    below one bin) and in between."""
    a = np.abs(yaw)
    return dict(yaw_saturated=round(float((a > 0.99).mean()), 3), yaw_zero=round(float((a < 1 / 128).mean()), 3),
                yaw_mid=round(float(((a >= 1 / 128) & (a <= 0.99)).mean()), 3))


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        gains = [float(g) for g in FLAGS.gains]
    except ValueError as e:
        raise app.UsageError(f"--gains must be numbers, got {FLAGS.gains}") from e
    if not gains or min(gains) <= 0:
        raise app.UsageError(f"--gains must be > 0, got {FLAGS.gains}")
    task_list = cli.task_list(FLAGS.suites)
    env = TabletopEnv(task_list, EnvConfig(render=False))
    n_steps = max(t.max_steps for t in task_list)
    tids = np.repeat(np.arange(len(task_list)), FLAGS.episodes)
    keys = env.initial_state_keys(tids, np.tile(np.arange(FLAGS.episodes), len(task_list)), split="train")
    suite_of = np.array([task_list[t].suite for t in tids])
    out = {}
    for g in gains:
        policy = expert.policy(env, expert.ExpertConfig(rot_gain=g))
        fn = jax.jit(lambda k, t, p=policy: rollout.record_episodes(env, p, k, t, n_steps,
                                                                   exec_noise=FLAGS.action_noise))
        t0 = time.perf_counter()
        final, traj = jax.block_until_ready(fn(keys, jnp.asarray(tids, jnp.int32)))
        success, steps = np.asarray(final.success), np.asarray(final.step)
        action = np.asarray(traj["action"])  # [T, B, 7]
        live = np.arange(action.shape[0])[:, None] < steps[None, :]
        per_suite = {s: dict(success=round(float(success[suite_of == s].mean()), 3),
                             steps_per_success=round(float(steps[(suite_of == s) & success].mean()), 1)
                             if success[suite_of == s].any() else None)
                     for s in sorted({str(s) for s in suite_of})}
        out[f"{g:g}"] = dict(success=round(float(success.mean()), 4),
                             steps_per_success=round(float(steps[success].mean()), 1) if success.any() else None,
                             **label_spread(action[..., 5][live]), per_suite=per_suite,
                             seconds=round(time.perf_counter() - t0, 1))
        print(f"rot_gain {g:g}: {out[f'{g:g}']}", flush=True)
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()),
                                                 "episodes": len(tids), "gains": out})


if __name__ == "__main__":
    cli.run(main)
