"""How confident and how batch-invariant the target is on its own closed-loop states.

  python -m experiments.studies.target_confidence --suites=all --envs=40 --steps=60 --out=results/confidence.json

Records greedy-AR rollouts of the target (--envs envs on the fixed evaluation initial states,
--steps control steps), then on every state where the episode still runs:
  - the probability the target gives its greedy token, per action dimension (teacher-forced
    on its own greedy tokens): quantiles and the share of tokens above 0.5 / 0.9;
  - AR replayed at batch 1 against AR at the recording's batch size on the same states: the
    share of states where all 7 tokens agree (near-flat logits flip with batch numerics).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import language, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import checkpoint, results_io, target_model, vla
from heisd_jax.harness import methods, vla_policy
from heisd_jax.tokenizer import ACTION_DIM
from experiments import cli

FLAGS = flags.FLAGS
cli.define_paths("checkpoint")
flags.DEFINE_string("suites", "all", "Suites whose tasks the envs cycle through.")
flags.DEFINE_integer("envs", 40, "Envs recorded in parallel (the batch AR is compared against).")
flags.DEFINE_integer("steps", 60, "Control steps recorded.")
flags.DEFINE_integer("batch1_states", 200, "States replayed at batch 1 (spread over the recording).")
flags.DEFINE_string("out", "results/target_confidence.json", "Results JSON.")
flags.DEFINE_enum("dtype", None, list(methods.DTYPES), "The target's " + methods.settings("ar")["dtype"].help)
flags.DEFINE_enum("matmul_precision", vla.VLAConfig.matmul_precision, list(vla.MATMUL_PRECISIONS),
                  "The target's " + methods.settings("ar")["matmul_precision"].help)


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    for name in ("envs", "steps", "batch1_states"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1")
    try:
        task_list = tasks_lib.get_tasks(FLAGS.suites)
        env = TabletopEnv(task_list, methods.env_config("ar", FLAGS.checkpoint))
        params, cfg, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    cfg, params = methods.in_dtype(cfg, FLAGS.dtype or cfg.dtype, params, matmul_precision=FLAGS.matmul_precision)
    policy = vla_policy.decoding_policy("ar", params, cfg, tok, vla_policy.ar)
    n = FLAGS.envs
    t0 = time.perf_counter()
    tids, traj = rollout.record_eval_starts(env, policy, n, FLAGS.steps)
    print(f"recorded {n} envs x {FLAGS.steps} steps in {time.perf_counter() - t0:.0f}s", flush=True)
    live = ~traj["done"]  # [T, B]
    instr = np.asarray(env.instructions)[tids]

    ar_batch = jax.jit(lambda p, o: target_model.ar_decode(p, cfg, o)[0])
    probs_fn = jax.jit(lambda p, o, t: _greedy_probs(p, cfg, o, t))
    tokens, probs, gaps = [], [], []
    for t in range(FLAGS.steps):  # AR at the recording's batch size, state by state in time
        obs = vla.Observation(image=jnp.asarray(traj["image"][t]), instruction=jnp.asarray(instr),
                              proprio=jnp.asarray(traj["proprio"][t]))
        tk = ar_batch(params, obs)
        tokens.append(np.asarray(tk))
        prob, gap = probs_fn(params, obs, tk)
        probs.append(np.asarray(prob))
        gaps.append(np.asarray(gap))
    tokens, probs, gaps = np.stack(tokens), np.stack(probs), np.stack(gaps)  # [T, B, 7]
    live_idx = np.argwhere(live)
    pick = live_idx[np.linspace(0, len(live_idx) - 1, min(FLAGS.batch1_states, len(live_idx))).astype(int)]
    same = []
    for t, b in pick:
        obs = vla.Observation(image=jnp.asarray(traj["image"][t, b:b + 1]), instruction=jnp.asarray(instr[b:b + 1]),
                              proprio=jnp.asarray(traj["proprio"][t, b:b + 1]))
        same.append(bool(np.array_equal(np.asarray(ar_batch(params, obs))[0], tokens[t, b])))
    p, g = probs[live], gaps[live]  # [N, 7]
    q = [0.05, 0.25, 0.5, 0.75, 0.95]
    summary = {
        "states": int(live.sum()),
        "greedy_prob_quantiles_per_dim": {str(k): [round(float(x), 4) for x in np.quantile(p, k, axis=0)] for k in q},
        "greedy_prob_mean_per_dim": [round(float(x), 4) for x in p.mean(0)],
        "share_above_0.5": round(float((p > 0.5).mean()), 4),
        "share_above_0.9": round(float((p > 0.9).mean()), 4),
        # How near the greedy token is to a tie: numeric noise of this size flips the choice.
        "top2_logit_gap_quantiles": {str(k): float(f"{np.quantile(g, k):.3g}") for k in (0.001, 0.01, 0.05, 0.5)},
        "share_top2_logit_gap_below": {str(x): round(float((g < x).mean()), 5) for x in (1e-4, 1e-3, 1e-2)},
        "batch1_vs_batch_states": len(same),
        "batch1_vs_batch_identical_actions": round(float(np.mean(same)), 4),
    }
    record = {**results_io.provenance(cli.command_line()), "batch": n, "dtype": cfg.dtype, "summary": summary}
    Path(FLAGS.out).parent.mkdir(parents=True, exist_ok=True)
    results_io.write_json_atomic(FLAGS.out, record)
    print(json.dumps(summary, indent=1))
    print(f"results: {os.path.abspath(FLAGS.out)}")


def _greedy_probs(params, cfg: vla.VLAConfig, obs: vla.Observation, tokens: jnp.ndarray):
    """([B, 7], [B, 7]): the probability of each greedy token under the target, teacher-forced,
    and the gap between its two largest action logits."""
    logits, _ = vla.forward(params, cfg, obs, tokens)
    p = cfg.prompt_len
    action_logits = vla.action_logits(cfg, logits[:, p - 1: p - 1 + ACTION_DIM])
    lp = jax.nn.log_softmax(action_logits, -1)
    top2 = jax.lax.top_k(action_logits, 2)[0]
    prob = jnp.exp(jnp.take_along_axis(lp, (tokens - cfg.first_action_id)[..., None], -1)[..., 0])
    return prob, top2[..., 0] - top2[..., 1]


if __name__ == "__main__":
    cli.run(main)
