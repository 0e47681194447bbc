"""Does the expanded target choose the shipped target's actions? On closed-loop states.

  python -m experiments.scale_check --target_scale=llama2-7b --dtypes=float32,bfloat16 --envs=64 --steps=20 \
      --batch1_states=1000 --out=results/scale_check.json

Records greedy-AR rollouts of the shipped target (--envs envs on the fixed evaluation initial
states, --steps control steps), then on every state where the episode still runs decodes the
action with the shipped target and with the target expanded to --target_scale in each of
--dtypes, at the recording's batch size (--envs), and for --batch1_states of those states
(spread over the recording) one at a time: the share of states whose 7 tokens are
identical, and the mean bin distance where they are not.
"""

from __future__ import annotations

import dataclasses
import json
import time

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from envs import language, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import checkpoint, results_io, scale, target_model, vla
from heisd_jax.harness import methods, vla_policy
from experiments import cli

FLAGS = flags.FLAGS
cli.define_paths("checkpoint")
flags.DEFINE_enum("target_scale", "llama2-7b", list(scale.SCALES), "Architecture the target is expanded to.")
flags.DEFINE_list("dtypes", ["float32", "bfloat16"], f"Expanded target dtypes, of {methods.DTYPES}.")
flags.DEFINE_string("suites", "all", "Suites whose tasks the envs cycle through.")
flags.DEFINE_integer("envs", 64, "Envs recorded in parallel (the batch size compared).")
flags.DEFINE_integer("steps", 20, "Control steps recorded.")
flags.DEFINE_integer("batch1_states", 1000, "States decoded one at a time (spread over the recording).")
flags.DEFINE_enum("attention", methods.Numerics.attention, [vla.AUTO_ATTENTION, *vla.ATTENTIONS],
                  "How the 16-bit expansions' prefill attends (a method's `attention`; auto: as a method's default, "
                  "cudnn on a GPU, vla.resolve_attention); float32 always attends with XLA's.")
flags.DEFINE_string("out", "results/scale_check.json", "Results JSON.")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    bad = [d for d in FLAGS.dtypes if d not in methods.DTYPES]
    if bad:
        raise app.UsageError(f"--dtypes: unknown {bad}; valid: {', '.join(methods.DTYPES)}")
    for name in ("envs", "steps"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1")
    try:
        vla.check_attention(FLAGS.attention)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    try:
        env = TabletopEnv(tasks_lib.get_tasks(FLAGS.suites), methods.env_config("ar", FLAGS.checkpoint))
        params, cfg, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
        for dtype in FLAGS.dtypes:
            scale.check_fits(cfg, FLAGS.target_scale, dtype)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    n = FLAGS.envs
    policy = vla_policy.decoding_policy("ar", params, cfg, tok, vla_policy.ar)
    t0 = time.perf_counter()
    tids, traj = rollout.record_eval_starts(env, policy, n, FLAGS.steps)
    print(f"recorded {n} envs x {FLAGS.steps} steps in {time.perf_counter() - t0:.0f}s", flush=True)
    live = ~traj["done"]  # [T, B]
    instr = np.asarray(env.instructions)[tids]
    obs_at = lambda t, rows=slice(None): vla.Observation(  # noqa: E731
        image=jnp.asarray(traj["image"][t, rows]), instruction=jnp.asarray(instr[rows]),
        proprio=jnp.asarray(traj["proprio"][t, rows]))
    live_idx = np.argwhere(live)
    pick = live_idx[np.linspace(0, len(live_idx) - 1, min(FLAGS.batch1_states, len(live_idx))).astype(int)]

    def decode_all(p, c):
        """Tokens [T, B, 7] at the recording's batch size, and [N, 7] of the picked states at batch 1."""
        fn = jax.jit(lambda p, o: target_model.ar_decode(p, c, o)[0])
        batch = np.stack([np.asarray(fn(p, obs_at(t))) for t in range(FLAGS.steps)])
        one = np.stack([np.asarray(fn(p, obs_at(t, slice(b, b + 1))))[0] for t, b in pick])
        return batch, one

    def write(summary):
        record = {**results_io.provenance(cli.command_line()), "scale": FLAGS.target_scale, "batch": n,
                  "summary": summary}
        results_io.write_json_atomic(FLAGS.out, record)

    ref_batch, ref_one = decode_all(params, cfg)
    summary = {"states": int(live.sum()), "batch1_states": len(pick),
               "shipped_batch1_vs_batch": float(np.mean(np.all(ref_one == ref_batch[pick[:, 0], pick[:, 1]], -1)))}
    for dtype in FLAGS.dtypes:
        t0 = time.perf_counter()
        big, big_cfg = scale.expand_target(params, cfg, FLAGS.target_scale, dtype)
        if dtype != "float32":
            big_cfg = dataclasses.replace(big_cfg, attention=vla.resolve_attention(FLAGS.attention, big_cfg))
        jax.block_until_ready(big)
        built = time.perf_counter() - t0
        batch, one = decode_all(big, big_cfg)
        del big
        same_b, same_1 = np.all(batch == ref_batch, -1)[live], np.all(one == ref_one, -1)
        dist_b = np.abs(batch - ref_batch)[live].mean(-1)
        summary[dtype] = {"identical_at_batch": float(same_b.mean()), "identical_at_batch1": float(same_1.mean()),
                          "mean_bin_distance_where_different": float(dist_b[~same_b].mean()) if (~same_b).any() else 0.0,
                          "attention": big_cfg.attention, "expand_seconds": round(built, 1)}
        print(f"{FLAGS.target_scale} {dtype}: identical to the shipped target on {same_b.mean():.2%} of {live.sum()} "
              f"states at batch {n}, {same_1.mean():.2%} of {len(pick)} at batch 1 (expanded in {built:.0f}s)",
              flush=True)
        write(summary)  # after each dtype: a run cut off keeps what it measured
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    cli.run(main)
