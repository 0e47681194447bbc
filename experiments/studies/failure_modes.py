"""Where a VLA's episodes go wrong: the expert watches every closed-loop step and says which
phase of the task the state is in.

  python -m experiments.studies.failure_modes --suites=all --episodes=10 --num_envs=400 \
      --out=results/failure_modes.json
  python -m experiments.studies.failure_modes --method=heisd --budget=fixed --continuation=ar \
      --suites=spatial --tasks=left_block_plate --episodes=30 --num_envs=10 --out=...

Runs a decoding method (default the target's greedy AR; any VLA method with its settings as
flags, as `experiments.evaluate` takes them) on the fixed evaluation initial states while the scripted expert,
acting alongside without control (DAgger's teacher at beta 0), labels each visited state with
its action and its phase (approach, descend, grasp, ...). Reports, per phase: the share of
steps, the mean absolute bin error between the policy's action and the expert's per action
dimension, and for the failed episodes the phase they ended in and whether the arm had
stopped moving (mean TCP speed over the last 20 steps under 1 cm/s). For a method that
skips verification (verify-skip), each episode's share of skipped steps, over the whole
episode and over its last 20 steps, and the traces mark the skipped steps.
"""

from __future__ import annotations

import collections
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import expert, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import results_io
from heisd_jax.harness import methods
from heisd_jax.tokenizer import ACTION_DIM
from experiments import cli, method_flags

FLAGS = flags.FLAGS
flags.DEFINE_enum("method", "ar", list(methods.DECODING_METHODS), "Decoding method (a VLA policy) to run.")
cli.define_paths("checkpoint", "drafter", "datastore")
for _name in method_flags.define():  # --top_k, --budget, ...: the VLA methods' settings
    flags.declare_key_flag(_name)
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names (default: every task of the suites).")
flags.DEFINE_integer("episodes", 10, "Evaluation initial states per task (0..49).")
flags.DEFINE_integer("num_envs", 400, "Episodes run in parallel.")
flags.DEFINE_integer("traces", 10, "Failed episodes whose step-by-step trace (every 5th step) goes into --out.")
flags.DEFINE_string("out", "", "Results JSON (optional).")

STUCK_SPEED = 0.01  # m/s
STUCK_WINDOW = 20  # control steps


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    if not 1 <= FLAGS.episodes <= tasks_lib.N_EVAL_INIT_STATES:
        raise app.UsageError(f"--episodes must be in 1..{tasks_lib.N_EVAL_INIT_STATES}, got {FLAGS.episodes}")
    if FLAGS.num_envs < 1:
        raise app.UsageError("--num_envs must be >= 1")
    kwargs = method_flags.given(FLAGS.method)
    try:
        task_list = tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
        env = TabletopEnv(task_list, methods.env_config(FLAGS.method, FLAGS.checkpoint))
        learner = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                      datastore=FLAGS.datastore, batch_size=FLAGS.num_envs, **kwargs)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    teacher = expert.observer(env)
    n_steps = int(max(t.max_steps for t in task_list))
    run = jax.jit(lambda p, k, t: _summarise(*rollout.record_episodes(
        env, dataclasses.replace(learner, params=p), k, t, n_steps, teacher=teacher, beta=0.0)))
    pairs = [(t, e) for t in range(len(task_list)) for e in range(FLAGS.episodes)]
    rows = []
    t0 = time.perf_counter()
    for start in range(0, len(pairs), FLAGS.num_envs):
        chunk = pairs[start: start + FLAGS.num_envs]
        tids, eps = np.array(chunk + [chunk[-1]] * (FLAGS.num_envs - len(chunk))).T
        out = jax.device_get(run(learner.params, env.initial_state_keys(tids, eps, split="eval"),
                                 jnp.asarray(tids, jnp.int32)))
        for i, (t, e) in enumerate(chunk):
            traced = sum("trace_phase" in r for r in rows)
            keep = {k: v[i] for k, v in out.items()
                    if not k.startswith("trace_") or (not out["success"][i] and traced < FLAGS.traces)}
            rows.append(dict(task=task_list[t].name, suite=task_list[t].suite, episode=int(e),
                             **{k: (np.round(v, 3) if np.issubdtype(v.dtype, np.floating) else v).tolist()
                                for k, v in keep.items()}))
        print(f"{len(rows)}/{len(pairs)} episodes, {time.perf_counter() - t0:.0f}s", flush=True)
    summary = _report(rows)
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, dict(settings=dict(method=FLAGS.method, **kwargs,
                                                                   checkpoint=FLAGS.checkpoint, suites=FLAGS.suites,
                                                                   tasks=[t.name for t in task_list],
                                                                   episodes=FLAGS.episodes),
                                                     summary=summary, episodes=rows))
        print(f"-> {FLAGS.out}")


def _summarise(final, traj):
    """Per-episode numbers from a recorded [T, B] trajectory (inside jit: only small arrays leave)."""
    running = ~traj["done"]  # [T, B]
    phase = traj["teacher_stats"]["phase"].astype(jnp.int32)
    goal = traj["teacher_stats"]["goal"].astype(jnp.int32)
    n_phases = len(expert.PHASE_NAMES)
    onehot = jax.nn.one_hot(phase, n_phases) * running[..., None]  # [T, B, P]
    err = jnp.abs(traj["policy_action"] - traj["action"]) * 127.5  # bins, [T, B, 7]
    last = jnp.maximum(final.step - 1, 0)  # index of the last running step, [B]
    take = lambda x: jnp.take_along_axis(x, last[None, :], axis=0)[0]  # noqa: E731
    mean_over = lambda x, mask: jnp.sum(x * mask, 0) / jnp.maximum(jnp.sum(mask, 0), 1)  # noqa: E731  [B]
    speed = jnp.linalg.norm(traj["ee_vel"], axis=-1)  # [T, B]
    t = jnp.arange(speed.shape[0])[:, None]
    window = running & (t > last[None, :] - STUCK_WINDOW)
    skipped = traj["stats"].get("skipped", jnp.zeros_like(speed)) * running  # [T, B], 0 without verify-skip
    return dict(
        success=final.success, steps=final.step,
        final_phase=take(phase), final_goal=take(goal),
        final_speed=mean_over(speed, window),
        skipped=mean_over(skipped, running),
        final_skipped=mean_over(skipped, window),
        phase_steps=jnp.sum(onehot, 0),  # [B, P]
        phase_err=jnp.einsum("tbp,tbd->bpd", onehot, err),  # [B, P, 7] summed bin error
        # Per-step trace (every 5th step): phase, TCP position and jaw (proprio), the policy's
        # action and the expert's, to read a failed episode step by step.
        trace_phase=phase[::5].T, trace_proprio=traj["proprio"][::5].transpose(1, 0, 2),
        trace_policy=traj["policy_action"][::5].transpose(1, 0, 2), trace_expert=traj["action"][::5].transpose(1, 0, 2),
        trace_skipped=skipped[::5].T,
    )


def _report(rows):
    names = expert.PHASE_NAMES
    by_suite = collections.defaultdict(list)
    for r in rows:
        by_suite[r["suite"]].append(r["success"])
    print("success: " + "  ".join(f"{s} {np.mean(v):.1%}" for s, v in by_suite.items()))
    steps = np.array([r["phase_steps"] for r in rows])  # [N, P]
    err = np.array([r["phase_err"] for r in rows])  # [N, P, 7]
    fail = np.array([not r["success"] for r in rows])
    phase_rows = []
    print(f"{'phase':<14}{'share':>7}{'fail share':>11}   mean |policy - expert| in bins: x y z roll pitch yaw grip")
    for p, name in enumerate(names):
        n = steps[:, p].sum()
        if n == 0:
            continue
        e = err[:, p].sum(0) / n
        phase_rows.append(dict(phase=name, share=float(n / steps.sum()),
                               fail_share=float(steps[fail, p].sum() / max(steps[fail].sum(), 1)), bin_error=e.tolist()))
        print(f"{name:<14}{n / steps.sum():>7.1%}{phase_rows[-1]['fail_share']:>11.1%}   "
              + " ".join(f"{x:5.1f}" for x in e))
    ends = collections.Counter((r["final_goal"], names[r["final_phase"]], r["final_speed"] < STUCK_SPEED)
                               for r in rows if not r["success"])
    print(f"failed episodes ({int(fail.sum())}) by (goal, phase at the end, arm stopped):")
    for (g, ph, stuck), c in ends.most_common():
        print(f"  goal {g} {ph:<14} {'stopped' if stuck else 'moving':<8} {c}")
    skip = np.array([r["skipped"] for r in rows])
    if skip.any():  # a method with verify-skip: do the failed episodes repeat actions unverified more?
        ok = f"{skip[~fail].mean():.1%}" if (~fail).any() else "none"
        print(f"skipped steps: {ok} of the successful episodes' steps; failed episodes "
              "(task, state, steps, skipped, skipped in the last 20 steps, TCP speed there):")
        for r in rows:
            if not r["success"]:
                print(f"  {r['task']} {r['episode']}: {r['steps']} steps, {r['skipped']:.0%}, {r['final_skipped']:.0%}, "
                      f"{100 * r['final_speed']:.1f} cm/s, ended in {names[r['final_phase']]}")
    return dict(success={s: float(np.mean(v)) for s, v in by_suite.items()}, phases=phase_rows,
                failure_ends=[dict(goal=int(g), phase=ph, stopped=bool(s), count=c) for (g, ph, s), c in ends.items()],
                action_dims=ACTION_DIM)


if __name__ == "__main__":
    cli.run(main)
