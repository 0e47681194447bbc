"""Pass costs of the target expanded to a larger architecture, against the hardware's limits.

  python -m experiments.bench_scale --target_scale=llama2-7b --dtype=bfloat16 --batch_sizes=1,16,64 \
      --out=results/bench_scale.json

Per batch size and pass kind (the prefill: vision tower + the prompt through the decoder; the
vision tower alone (the prompt's embeddings: what of the prefill the decoder does not do);
one cached token; a verification pass of T tokens under a causal mask; the prefill with T
candidate tokens appended; one drafter pass over T tokens), the median wall time of a jitted
call and (--in_graph) its marginal cost inside a compiled loop, which a decode loop pays per
pass without the call's dispatch, the seconds of its first call (its compile, or its load from
JAX's compilation cache, and one run: what a layout or an XLA flag costs to compile), the
bytes it must read (weights it touches, and the KV cache it attends over) and the FLOPs it
must do, and so the achieved bandwidth and FLOP/s with their fractions of the
device's peak (`PEAKS`; H100 SXM and H200: bf16 dense 989 TFLOP/s, HBM 3.35 / 4.8 TB/s).
Inputs are zeros and the cache is full length: costs do not depend on values.
"""

from __future__ import annotations

import dataclasses
import json

from absl import app, flags, logging

import jax
import jax.numpy as jnp

from heisd_jax import checkpoint, drafter, results_io, scale, timing, vla
from heisd_jax.observation import Observation
from experiments import cli

FLAGS = flags.FLAGS
cli.define_paths("checkpoint", "drafter")
flags.DEFINE_enum("target_scale", "llama2-7b", list(scale.SCALE_NAMES), "Architecture the target is expanded to.")
flags.DEFINE_enum("dtype", "bfloat16", ["float32", "bfloat16"], "Parameters, activations and cache dtype.")
flags.DEFINE_list("batch_sizes", ["1", "16", "64"], "Batch sizes.")
cli.positive_int_list("batch_sizes")
flags.DEFINE_list("verify_tokens", ["8", "48"], "Token counts of the verification and drafter passes.")
cli.positive_int_list("verify_tokens")
flags.DEFINE_integer("candidates", 28, "Candidate tokens appended to the prefill (4 actions of 7).")
flags.DEFINE_enum("layout", "per_layer", ["per_layer", "scan", "unrolled_scan"], "Decoder weights: one array per "
                  "layer (the expansion's), or stacked under a scan (the trained checkpoints'), rolled or unrolled.")
flags.DEFINE_enum("attention", vla.VLAConfig.attention, list(vla.ATTENTIONS), "How a pass without a cache (the "
                  "prefill) attends: XLA's fused products and softmax, or cuDNN's fused attention (GPU, bfloat16).")
flags.DEFINE_list("passes", [], "Pass kinds to time (vision, prefill, decode, prefill+block, verifyT, drafterT); "
                  "empty: all.")
flags.DEFINE_integer("reps", 10, "Timed calls per pass (median).")
flags.DEFINE_bool("in_graph", True, "Also time each pass inside a compiled loop (no per-call dispatch: what a "
                  "decode loop pays per pass; `heisd_jax.timing.in_graph_ms`).")
flags.DEFINE_string("trace_dir", "", "Trace 3 calls of each pass at the smallest batch size here and list its "
                    "largest kernels.")
flags.DEFINE_integer("top", 15, "Kernels listed per pass with --trace_dir.")
flags.DEFINE_string("out", "", "JSON output path.")

# device kind substring -> (HBM bytes/s, dense bf16 FLOP/s)
PEAKS = {"H100": (3.35e12, 989e12), "H200": (4.8e12, 989e12)}


def _peaks():
    kind = jax.devices()[0].device_kind
    return next((v for k, v in PEAKS.items() if k in kind), (None, None))


def layer_params(cfg: vla.VLAConfig) -> int:
    d, m = cfg.d_model, cfg.mlp_dim
    return 4 * d * d + 3 * d * m + 2 * d


def pass_cost(cfg: vla.VLAConfig, kind: str, b: int, t: int) -> tuple[float, float]:
    """(bytes read, FLOPs) of one pass over b rows of t new tokens: every weight it uses once,
    the KV cache it attends over (all slots: masked slots are read too), and the products."""
    byte = jnp.dtype(cfg.dtype).itemsize
    d, s, n_l = cfg.d_model, cfg.cache_slots, cfg.n_layers
    dec_w = n_l * layer_params(cfg) + d * cfg.vocab  # layers and head
    logits_tokens = (1 + (t if kind == "prefill+block" else 0)) if kind.startswith("prefill") else t
    if kind == "drafter":
        w = layer_params(cfg) + 2 * d * d
        flops = 2 * b * t * w + 2 * b * t * d * 256
        return (w + 2 * b * s * d) * byte, flops + 4 * b * t * (s + t) * d
    vw = cfg.vision_width
    vis_w = cfg.vision_layers * (4 * vw * vw + 3 * vw * cfg.vision_mlp) + vw * d
    vis_flops = 2 * b * cfg.image_tokens * vis_w + 4 * b * cfg.vision_layers * cfg.image_tokens ** 2 * vw
    if kind == "vision":
        return vis_w * byte, vis_flops
    if kind.startswith("prefill"):
        p = cfg.prompt_len + (t if kind == "prefill+block" else 0)
        flops = (2 * b * p * n_l * layer_params(cfg) + 2 * b * logits_tokens * d * cfg.vocab
                 + 4 * b * n_l * p * p * d + vis_flops)
        return (dec_w + vis_w) * byte, flops
    kv = 2 * n_l * b * s * d * byte
    flops = 2 * b * t * n_l * layer_params(cfg) + 2 * b * t * d * cfg.vocab + 4 * b * n_l * t * (s + t) * d
    return dec_w * byte + kv, flops


def _observation(cfg: vla.VLAConfig, b: int) -> Observation:
    return Observation(image=jnp.zeros((b, *cfg.image_shape), jnp.uint8),
                       instruction=jnp.ones((b, cfg.text_len), jnp.int32), proprio=jnp.zeros((b, cfg.proprio_dim)))


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    tokens = sorted({int(x) for x in FLAGS.verify_tokens})
    valid = (["vision", "prefill", "decode", "prefill+block"]
             + [f"{k}{t}" for k in ("verify", "drafter") for t in tokens])
    if set(FLAGS.passes) - set(valid):
        raise app.UsageError(f"--passes: unknown {sorted(set(FLAGS.passes) - set(valid))}; valid: {valid}")
    params, cfg0, _, _ = checkpoint.load_policy(FLAGS.checkpoint)
    try:
        vla.check_attention(FLAGS.attention)
        dataclasses.replace(cfg0, dtype=FLAGS.dtype, attention=FLAGS.attention)  # refuses cudnn in float32
        scale.check_fits(cfg0, FLAGS.target_scale, FLAGS.dtype)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    dparams, _ = checkpoint.load_drafter(FLAGS.drafter, cfg0, params)
    dparams = scale.expand_drafter(dparams, cfg0, FLAGS.target_scale, FLAGS.dtype)
    params, cfg = scale.expand_target(params, cfg0, FLAGS.target_scale, FLAGS.dtype)
    params, cfg = scale.with_layout(params, cfg, per_layer=FLAGS.layout == "per_layer")
    cfg = dataclasses.replace(cfg, unroll=FLAGS.layout == "unrolled_scan", attention=FLAGS.attention)
    counts = scale.n_params(cfg)
    bw, peak = _peaks()
    print(f"{FLAGS.target_scale} {FLAGS.dtype} on {jax.devices()[0].device_kind}: decoder "
          f"{counts['decoder'] / 1e9:.2f}B, vision {counts['vision'] / 1e9:.2f}B parameters; prompt {cfg.prompt_len}, "
          f"cache {cfg.cache_slots} slots", flush=True)
    # the pure pieces (in-graph timing loops them), and their jitted calls
    pieces = {"vision": lambda p, o: vla.prompt_embeddings(p, cfg, o),
              "prefill": lambda p, o: vla.prefill(p, cfg, o)[0],
              "prefill+block": lambda p, o, tk, dp, m: vla.prefill_with_block(p, cfg, o, tk, dp, m)[0],
              "decode": lambda p, c, tk, dp, m: vla.cached_pass(p, cfg, c, tk, dp, m)[0],
              "drafter": lambda dp, c, e, pos, slot, m: drafter.cached_pass(dp, cfg, c, e, e, pos, slot, m)[0]}
    jitted = {k: jax.jit(f) for k, f in pieces.items()}
    prefill_cache = jax.jit(lambda p, o: vla.prefill(p, cfg, o)[2])
    rows = []
    batches = sorted({int(x) for x in FLAGS.batch_sizes})
    for b in batches:
        obs = _observation(cfg, b)
        cache = prefill_cache(params, obs)
        full = cache.replace(key_mask=jnp.ones_like(cache.key_mask), length=jnp.full((b,), cfg.prompt_len, jnp.int32))
        dcache = drafter.init_cache(cfg, b).replace(length=full.length, key_mask=full.key_mask)

        def causal(t):
            tk = jnp.full((b, t), cfg.first_action_id, jnp.int32)
            return tk, jnp.broadcast_to(jnp.arange(t), (b, t)), jnp.broadcast_to(vla.causal_mask(t, t), (b, t, t))

        # pass kind -> (new tokens, piece, its arguments)
        calls = {"vision": (0, "vision", (params, obs)), "prefill": (1, "prefill", (params, obs)),
                 "decode": (1, "decode", (params, full, *causal(1))),
                 "prefill+block": (FLAGS.candidates, "prefill+block", (params, obs, *causal(FLAGS.candidates)))}
        for t in tokens:
            calls[f"verify{t}"] = (t, "decode", (params, full, *causal(t)))
            emb = jnp.zeros((b, t, cfg.d_model), cfg.dtype)
            pos = cfg.prompt_len + jnp.broadcast_to(jnp.arange(t), (b, t))
            calls[f"drafter{t}"] = (t, "drafter", (dparams, dcache, emb, pos, full.length,
                                                   jnp.ones((b, t, cfg.cache_slots), bool)))
        for kind, (t, piece, args) in calls.items():
            if FLAGS.passes and kind not in FLAGS.passes:
                continue
            fn = lambda piece=piece, args=args: jitted[piece](*args)  # noqa: E731
            first_s = timing.timed(fn)[1]  # compile (or a compilation-cache load) and one run
            ms = 1e3 * timing.median_seconds(fn, FLAGS.reps)
            nbytes, flops = pass_cost(cfg, piece, b, t)
            row = {"batch": b, "pass": kind, "tokens": t, "ms": ms, "first_call_s": first_s, "bytes": nbytes,
                   "flops": flops, "bandwidth_TBps": nbytes / ms / 1e9, "TFLOPps": flops / ms / 1e9}
            if FLAGS.in_graph:
                row["loop_ms"] = timing.in_graph_ms(pieces[piece], args, n=(1, 4), reps=3)
            if bw:
                row.update(roofline_ms=1e3 * max(nbytes / bw, flops / peak), bandwidth_share=row["bandwidth_TBps"] * 1e12 / bw,
                           flops_share=row["TFLOPps"] * 1e12 / peak)
                row["x_roofline"] = ms / row["roofline_ms"]
                if "loop_ms" in row:
                    row["loop_x_roofline"] = row["loop_ms"] / row["roofline_ms"]
            if FLAGS.trace_dir and b == batches[0]:
                path = timing.trace_calls(fn, 3, f"{FLAGS.trace_dir}/{kind}_b{b}")
                row["kernels"] = timing.kernel_summary(path, 3, FLAGS.top) if path else {}
            rows.append(row)
            extra = (f"  {row['bandwidth_share']:5.1%} of HBM  {row['flops_share']:5.1%} of bf16 peak  "
                     f"{row['x_roofline']:.2f}x roofline") if bw else ""
            if "loop_ms" in row:
                extra += f"; in a loop {row['loop_ms']:.3f} ms" + (f" ({row['loop_x_roofline']:.2f}x)" if bw else "")
            print(f"B={b:<4} {kind:<14} {ms:9.3f} ms  {row['bandwidth_TBps']:6.2f} TB/s  {row['TFLOPps']:7.1f} TFLOP/s"
                  + extra + f"; first call {first_s:.1f} s", flush=True)
            for line, summary in row.get("kernels", {}).items():
                print(f"    kernels, {line}: {summary['total_ms']:.3f} ms per call, {summary['count']} events")
                for kname, kms in summary["top"]:
                    print(f"      {kms:9.3f}  {kname[:120]}")
        if FLAGS.out:
            results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()),
                                                     "scale": FLAGS.target_scale, "dtype": FLAGS.dtype,
                                                     "layout": FLAGS.layout, "attention": FLAGS.attention,
                                                     "params": counts, "rows": rows})
    print(json.dumps({"params": counts}))


if __name__ == "__main__":
    cli.run(main)
