"""How much the target's actions repeat from one control step to the next: what the env's own
recent actions can offer as retrieval candidates, and what repeating the last action without
a target pass (a verify-skip on the recent candidate) would cost.

  python -m experiments.studies.action_repeats --suites=all --record_envs=16 --steps=100

Records AR's closed-loop actions as `bench_methods` does (`heisd_jax.harness.replay.record`), then
reports, over steps where the episode runs:
  - per dimension, the bin distance between consecutive actions;
  - how often the previous action, as a draft, would be accepted whole by HeiSD's
    sequence-wise rule (`acceptance.seq_relaxed_length`, the paper's r_max 15 / r_seq 42) against the
    action the target emitted (an approximation: in a real verification the target's tokens
    are conditioned on the draft's prefix, not on its own);
  - that share after k consecutive whole repeats (are repeats bursty?);
  - a host simulation of "repeat the last verified action without a target pass once the last
    n_confirm verified steps each repeated their predecessor, at most k_skip times in a row":
    the share of skipped steps and how many of them fall outside the rule's tolerance.
"""

from __future__ import annotations

from pathlib import Path

from absl import flags

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax.numpy as jnp
import numpy as np

from envs import language, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import acceptance, checkpoint, hybrid, results_io
from heisd_jax.harness import methods, replay
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "goal", f"Suites of {list(tasks_lib.SUITES)} or 'all'.")
flags.DEFINE_integer("record_envs", 16, "Recorded envs.")
flags.DEFINE_integer("steps", 100, "Recorded control steps per env.")
cli.define_paths("checkpoint")
flags.DEFINE_string("out", "", "JSON output path.")


def whole(draft: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[...] the draft action [..., 7] (bins) accepted whole against the target's [..., 7]."""
    cfg = hybrid.PAPER.seq
    return np.asarray(acceptance.seq_relaxed_length(jnp.asarray(draft), jnp.asarray(target), cfg)) == 7


def simulate_repeat_skip(bins: np.ndarray, live: np.ndarray, n_confirm: int, k_skip: int) -> tuple[float, float]:
    """(share of steps skipped, share of skipped steps outside tolerance) over bins [T, B, 7]."""
    steps = skipped = outside = 0
    for e in range(bins.shape[1]):
        last, streak, run = None, 0, 0
        for t in range(bins.shape[0]):
            if not live[t, e]:
                break
            steps += 1
            if last is not None and streak >= n_confirm and run < k_skip:
                skipped, run = skipped + 1, run + 1
                outside += not whole(last, bins[t, e])
                continue
            run = 0
            if last is not None:
                streak = streak + 1 if whole(last, bins[t, e]) else 0
            last = bins[t, e]
    return skipped / max(steps, 1), outside / max(skipped, 1)


def measure(bins: np.ndarray, live: np.ndarray) -> dict:
    """The figures the module doc lists, from AR's action bins [T, B, 7] and live [T, B]."""
    pair = live[1:] & live[:-1]  # [T-1, B]
    diff = np.abs(bins[1:] - bins[:-1])[pair]  # [n, 7]
    rep = whole(bins[:-1], bins[1:]) & pair  # [T-1, B]
    after = {}
    for k in (1, 2, 3):
        cond = pair[k:].copy()
        for j in range(1, k + 1):
            cond &= rep[k - j: len(rep) - j]
        after[k] = {"accepted_whole": float(rep[k:][cond].mean()) if cond.any() else None, "steps": int(cond.sum())}
    skip = []
    for n_confirm in (1, 2, 3):
        for k_skip in (1, 3, 5):
            share, out = simulate_repeat_skip(bins, live, n_confirm, k_skip)
            skip.append({"n_confirm": n_confirm, "k_skip": k_skip, "skipped": share, "outside_tolerance": out})
    return {"pairs": int(diff.shape[0]), "bin_distance_mean": diff.mean(0).tolist(),
            "bin_distance_median": np.median(diff, 0).tolist(),
            "within_bins": {r: {"per_dim": (diff <= r).mean(0).tolist(), "all": float((diff <= r).all(-1).mean())}
                            for r in (0, 3, 9, 15)},
            "previous_accepted_whole": float(rep[pair].mean()), "after_whole_repeats": after,
            "repeat_skip": skip}


def main(argv):
    del argv
    env = TabletopEnv(tasks_lib.get_tasks(FLAGS.suites), methods.env_config("ar", FLAGS.checkpoint))
    _, actions, done = replay.record(env, methods.make_policy("ar", env, checkpoint=FLAGS.checkpoint),
                                     FLAGS.record_envs, FLAGS.steps)
    _, _, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    bins = np.asarray(tok.to_bins(np.asarray(actions))).astype(np.int32)  # [T, B, 7]
    m = measure(bins, ~np.asarray(done))
    print(f"{FLAGS.record_envs} envs x {FLAGS.steps} steps of AR ({FLAGS.suites}): {m['pairs']} consecutive pairs")
    print("bin distance to the previous action, per dimension (dx dy dz droll dpitch dyaw gripper):")
    print(f"  mean   {np.round(m['bin_distance_mean'], 2)}")
    print(f"  median {np.asarray(m['bin_distance_median'])}")
    for r, w in m["within_bins"].items():
        print(f"  within {r:2d} bins: {np.round(w['per_dim'], 3)}, all 7: {w['all']:.3f}")
    print(f"previous action accepted whole (seq_relaxed, r_max 15, r_seq 42): {m['previous_accepted_whole']:.3f}")
    for k, a in m["after_whole_repeats"].items():
        print(f"  after {k} whole repeats in a row: {a['accepted_whole']} ({a['steps']} steps)")
    print("repeat the last verified action without a target pass (host simulation):")
    for r in m["repeat_skip"]:
        print(f"  n_confirm {r['n_confirm']} k_skip {r['k_skip']}: {r['skipped']:.3f} of steps skipped, "
              f"{r['outside_tolerance']:.3f} of them outside the tolerance")
    if FLAGS.out:
        Path(FLAGS.out).parent.mkdir(parents=True, exist_ok=True)
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), **m})


if __name__ == "__main__":
    cli.run(main)
