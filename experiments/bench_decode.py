"""Decoding cost of the target VLA, per batch size, in one run: the AR baseline every
speculative method is compared against.

  python -m experiments.bench_decode --batch_sizes=1,16,256 --out=results/bench_decode.json

Per batch size B, with the shipped checkpoint's parameters and random observations, it times
(compiled once, warm-up excluded, `block_until_ready`, median of --reps timed calls):
  prefill      one pass over the prompt (vision encoder + visual/text/proprio tokens) -> first token
  decode1      one cached single-token pass (AR does 6 of these after the prefill)
  ar_action    the whole greedy AR decode of one action (prefill + 6 decode passes, one jitted call)
and reports AR latency per action, AR actions per second (B / ar_action), and the share of
the prefill: AR / prefill is the ceiling of any speculative method, since every action
needs at least one target pass over a new image.

With --drafter (and --demos for real observations: acceptance depends on them), it also
times drafter-based speculative decoding (one jitted call per action) for each acceptance
setting of --relax_bins (0 = strict), with its target passes per action and its speedup
over AR measured in the same run:

  python -m experiments.bench_decode --drafter=checkpoints/drafter --demos=data/demos --relax_bins=0,9
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flag before JAX starts)
from envs import demos, language
from heisd_jax.timing import median_seconds
from heisd_jax import checkpoint, results_io, spec_decode, target_model, vla
from heisd_jax.harness import data
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["1", "16", "256"], "Batch sizes (rows decoded together).")
cli.positive_int_list("batch_sizes")
flags.DEFINE_integer("reps", 30, "Timed calls per measurement (the median is reported).")
cli.define_paths("checkpoint")
flags.DEFINE_enum("dtype", "", ["", "float32", "bfloat16"], "Compute dtype override (default: the checkpoint's).")
flags.DEFINE_string("drafter", "", "Drafter checkpoint: also time speculative decoding.")
cli.existing_dir("drafter", "drafter checkpoint")
flags.DEFINE_string("demos", "", "Demos dataset to draw observations from (default: random observations).")
cli.existing_dir("demos", "demonstrations dataset")
flags.DEFINE_list("relax_bins", ["0", "9"], "Acceptance settings timed with --drafter (0: strict, r > 0: token_relaxed).")
flags.DEFINE_integer("top_k", 8, "Draft tree top-k.")
flags.DEFINE_integer("depth", 4, "Draft tree depth.")
flags.DEFINE_integer("total_tokens", 32, "Draft tree nodes verified per round.")
flags.DEFINE_string("out", "", "Optional JSON output path.")


def random_observation(cfg: vla.VLAConfig, batch: int, seed: int = 0) -> vla.Observation:
    rng = np.random.default_rng(seed)
    return vla.Observation(
        image=jnp.asarray(rng.integers(0, 256, (batch, *cfg.image_shape), np.uint8)),
        instruction=jnp.asarray(rng.integers(1, cfg.text_vocab, (batch, cfg.text_len)), jnp.int32),
        proprio=jnp.asarray(rng.normal(size=(batch, cfg.proprio_dim)), jnp.float32))


def demo_observation(path: str, batch: int, seed: int = 0) -> vla.Observation:
    ds = demos.DemoDataset(path)
    eps = np.random.default_rng(seed).permutation(len(ds))[: max(1, min(len(ds), batch // 8 + 1))]
    t = data.load_steps(path, sorted(eps.tolist()))
    i = np.random.default_rng(seed + 1).integers(0, t.size, batch)
    return vla.Observation(image=jnp.asarray(t.image[i]), instruction=jnp.asarray(t.instruction[i]),
                           proprio=jnp.asarray(t.proprio[i]))


def bench(params, cfg: vla.VLAConfig, batch: int, reps: int, dparams=None) -> dict:
    obs = demo_observation(FLAGS.demos, batch) if FLAGS.demos else random_observation(cfg, batch)
    prefill = jax.jit(lambda p, o: vla.prefill(p, cfg, o))
    _, _, cache = prefill(params, obs)
    tok = jnp.full((batch, 1), cfg.first_action_id, jnp.int32)
    decode1 = jax.jit(lambda p, c, t: vla.cached_pass(p, cfg, c, t, jnp.zeros((batch, 1), jnp.int32),
                                                 jnp.ones((batch, 1, 1), bool))[0])
    ar = jax.jit(lambda p, o: target_model.ar_decode(p, cfg, o)[0])
    t = {"prefill": median_seconds(lambda: prefill(params, obs)[0], reps),
         "decode1": median_seconds(lambda: decode1(params, cache, tok), reps),
         "ar_action": median_seconds(lambda: ar(params, obs), reps)}
    row = {"batch": batch, "ms": {k: round(v * 1e3, 4) for k, v in t.items()},
           "ar_actions_per_s": batch / t["ar_action"], "prefill_share_of_ar": t["prefill"] / t["ar_action"],
           "speculation_ceiling": t["ar_action"] / t["prefill"], "speculative": []}
    if dparams is not None:
        ar_tokens = ar(params, obs)
        for r in (int(x) for x in FLAGS.relax_bins):
            spec = spec_decode.SpecConfig(top_k=FLAGS.top_k, depth=FLAGS.depth, total_tokens=FLAGS.total_tokens,
                                          acceptance="token_relaxed" if r else "strict", relax_bins=r)
            fn = jax.jit(lambda p, d, o, spec=spec: spec_decode.spec_decode(p, d, cfg, spec, o))
            tokens, stats = fn(params, dparams, obs)
            sec = median_seconds(lambda: fn(params, dparams, obs)[0], reps)
            row["speculative"].append({
                "acceptance": spec.acceptance, "relax_bins": r, "ms_per_action": round(sec * 1e3, 4),
                "speedup_vs_ar": t["ar_action"] / sec,
                "target_passes_per_action": float(stats["target_passes"].mean()),
                "drafter_passes_per_action": float(stats["drafter_passes"].mean()),
                "tokens_per_target_pass": 7.0 / float(stats["target_passes"].mean()),
                "identical_to_ar": float(jnp.mean(jnp.all(tokens == ar_tokens, -1)))})
    return row


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        params, cfg, _, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
        dparams = checkpoint.load_drafter(FLAGS.drafter, cfg, params)[0] if FLAGS.drafter else None
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    if FLAGS.dtype:
        cfg = vla.VLAConfig(**{**cfg.__dict__, "dtype": FLAGS.dtype})
    device = jax.devices()[0]
    print(f"target VLA {sum(x.size for x in jax.tree.leaves(params)) / 1e6:.2f}M params, {cfg.n_layers} layers, "
          f"prompt {cfg.prompt_len} tokens, {cfg.dtype}, on {device.device_kind}")
    rows = []
    for b in (int(x) for x in FLAGS.batch_sizes):
        r = bench(params, cfg, b, FLAGS.reps, dparams)
        rows.append(r)
        print(f"B={b:<5} prefill {r['ms']['prefill']:8.3f} ms  decode1 {r['ms']['decode1']:8.3f} ms  "
              f"AR/action {r['ms']['ar_action']:8.3f} ms  ({r['ar_actions_per_s']:9.0f} actions/s)  "
              f"prefill share {r['prefill_share_of_ar']:.2f}  ceiling {r['speculation_ceiling']:.2f}x", flush=True)
        for sp in r["speculative"]:
            print(f"        drafter {sp['acceptance']:<13} r={sp['relax_bins']:<3} {sp['ms_per_action']:8.3f} ms/action  "
                  f"{sp['speedup_vs_ar']:.2f}x AR  target passes/action {sp['target_passes_per_action']:.2f}  "
                  f"AL {sp['tokens_per_target_pass']:.2f}  identical to AR {sp['identical_to_ar']:.2f}", flush=True)
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "dtype": cfg.dtype,
                                                 "jax": jax.__version__, "rows": rows})


if __name__ == "__main__":
    cli.run(main)
