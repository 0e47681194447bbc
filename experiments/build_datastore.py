"""Builds HeiSD's retrieval datastore from demonstrations, for the target checkpoint.

  python -m experiments.build_datastore --demos=data/demos --out=checkpoints/datastore

Keys: the last --history actions and the proprio vector; values: the next action's tokens
under the target's tokenizer (--values: the demo's, the target's own, or, from the target's
own rollouts, what it executed) (built by heisd_jax/harness/offline/datastore.py, loaded by
heisd_jax/retrieval.py). Every 1/--holdout-th episode is left out (listed in meta.json) for
experiments.calibrate_boundary; the kinematic metric's per-feature scales (90th percentile
over the datastore's demo steps) are saved with it. The datastore records the target's
fingerprint and is refused for any other target. An existing --out is replaced only once
the new one is complete, and only with --overwrite.
"""

from __future__ import annotations

import os
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import demos, language
from heisd_jax import checkpoint, kinematics, retrieval
from heisd_jax.harness.offline import datastore
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_string("demos", "data/demos", "Demonstrations dataset (experiments.collect_demos).")
cli.existing_dir("demos", "demonstrations dataset")
cli.define_paths("checkpoint")
flags.DEFINE_string("out", "checkpoints/datastore", "Output directory.")
flags.DEFINE_integer("history", 2, "Previous actions in each key.")
flags.DEFINE_float("pos_scale", 10.0, "Weight of end-effector position in the key, per metre.")
flags.DEFINE_float("holdout", 0.1, "Share of demo episodes left out of the datastore (every 1/holdout-th), "
                   "for experiments.calibrate_boundary.")
flags.DEFINE_enum("values", "demo", list(datastore.VALUES),
                  "Values: the demo's next action; the target's own greedy action on that step's observation; "
                  "or, for episodes the target drove alone (collect_demos --policy=TARGET --beta=0 --action_noise=0), "
                  "the target's action in the keys' histories too (what it executed there, not the expert's labels).")
flags.DEFINE_integer("stride", 1, "Keep every stride-th step (smaller datastore; the shipped one uses 2).")
flags.DEFINE_bool("overwrite", False, "Replace an existing datastore at --out.")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    if Path(FLAGS.out).exists() and not FLAGS.overwrite:
        raise app.UsageError(f"{FLAGS.out} exists; pass --overwrite to replace it (only once the new one is complete)")
    if FLAGS.history < 0 or FLAGS.pos_scale <= 0:
        raise app.UsageError("--history must be >= 0 and --pos_scale > 0")
    params, cfg, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    spec = retrieval.KeySpec(history=FLAGS.history, pos_scale=FLAGS.pos_scale)
    try:
        n = len(demos.DemoDataset(FLAGS.demos))
        keep, held = datastore.strided_episode_split(n, FLAGS.holdout)
        executed = datastore.executed_actions(params, cfg, tok, FLAGS.demos, keep) if FLAGS.values == "rollout" else None
        store = datastore.build_from_demos(FLAGS.demos, spec, tok, keep, actions=executed)
        if FLAGS.values == "target":
            store = datastore.with_values(store, datastore.target_values(params, cfg, FLAGS.demos, keep))
        store = datastore.subsample(store, FLAGS.stride)
        scales = kinematics.scales_from_demos(datastore.demo_features(FLAGS.demos, keep))
    except (FileNotFoundError, ValueError) as e:
        raise app.UsageError(str(e)) from e
    datastore.save(FLAGS.out, store, spec, tok, checkpoint.fingerprint(params),
                   extra={"demos": os.path.abspath(FLAGS.demos), "holdout_episodes": held,
                          "metric_scales": list(scales), "stride": FLAGS.stride, "values": FLAGS.values, "metric_features": list(kinematics.FEATURES)})
    size = sum(f.stat().st_size for f in Path(FLAGS.out).iterdir())
    print(f"datastore: {store.size} entries, key dim {spec.dim}, {size / 2**20:.1f} MiB -> {FLAGS.out}")


if __name__ == "__main__":
    cli.run(main)
