"""Where one decode call's device time goes, per kernel, at large batch sizes.

  python -m experiments.studies.trace_decode --batch_sizes=256,1024 --tree=4x2x8 --trace_dir=/tmp/trace
  python -m experiments.studies.trace_decode --method=heisd:budget=fixed,target_scale=llama2-7b,dtype=bfloat16 \
      --batch_sizes=1

With the shipped target and drafter (at --method's numerics: its dtype and `target_scale`) on
random observations (`cost_model.synthetic_inputs`), per batch size, each of these jitted calls
is timed (median wall time of --reps calls,
after a warm-up) and then traced with `jax.profiler` for --trace_calls calls:
  ar          greedy AR decoding (`target_model.ar_decode`)
  prefill     the target's prompt pass (`vla.prefill_features`)
  prefill_blk the prompt pass with the retrieval candidates appended (fused verification)
  zero_round  the HeiSD decode (`hybrid.decode` with --method's config, --tree) with every
              candidate equal to the target's own greedy action: accepted whole, no draft
              round; what an option's decode costs besides its rounds
  random      the same decode on random candidates (several draft rounds)
Each trace is summarised from its Perfetto JSON: the device's time per call, and the
kernels (or XLA ops) that take most of it, per device timeline. `zero_round` minus
`prefill_blk` is the decode's cost outside both the target pass and the rounds. With
--hlo_dir, each call's optimised HLO is written there too (gzipped text), to map kernel
names to the program. On the CPU the device timelines are the XLA threads.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import language
from heisd_jax import budget, checkpoint, cost_model, hybrid, results_io, target_model, timing, vla
from heisd_jax.harness import methods
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["256", "1024"], "Batch sizes.")
cli.positive_int_list("batch_sizes")
flags.DEFINE_string("method", "heisd:budget=fixed",
                    "The HybridConfig traced: a hybrid method and its settings (numerics included).")
FUNCTIONS = ("ar", "prefill", "prefill_blk", "zero_round", "random")
flags.DEFINE_list("functions", list(FUNCTIONS), f"Which calls to time and trace, of {list(FUNCTIONS)}.")
flags.DEFINE_string("tree", "", "The HeiSD decode's draft tree, TOPKxDEPTHxTOTAL (empty: the method's).")
flags.DEFINE_integer("reps", 5, "Timed calls per function (median).")
flags.DEFINE_integer("trace_calls", 2, "Calls per function inside its trace (0: no traces).")
flags.DEFINE_integer("top", 15, "Kernels listed per function and device timeline.")
flags.DEFINE_string("trace_dir", "/tmp/heisd_trace", "Where the traces go (one folder per function and batch).")
flags.DEFINE_string("hlo_dir", "", "Also write each function's optimised HLO here.")
flags.DEFINE_string("out", "", "Optional JSON with the timings and kernel summaries.")
cli.define_paths("checkpoint", "drafter")


def functions(params, cfg: vla.VLAConfig, hcfg: hybrid.HybridConfig, batch: int, names=FUNCTIONS):
    """{name: (jitted fn, args)} for the calls in the module doc that `names` lists (AR runs
    once here only where `zero_round` needs its actions)."""
    tp = params["target"]
    n = hcfg.n_verified
    obs, cand = cost_model.synthetic_inputs(cfg, batch, n)
    valid = jnp.ones((batch, n), bool)
    use, skip = jnp.ones((batch,), bool), jnp.zeros((batch,), bool)
    ar = jax.jit(lambda tp, obs: target_model.ar_decode(tp, cfg, obs)[0])
    dec = jax.jit(lambda p, obs, cand: hybrid.decode(p, cfg, hcfg, obs, cand, valid, use, skip))
    blk = jax.jit(lambda tp, obs, cand: vla.prefill_with_block(tp, cfg, obs, *hybrid.candidate_block(cand)))
    calls = {"ar": lambda: (ar, (tp, obs)),
             "prefill": lambda: (jax.jit(lambda tp, obs: vla.prefill_features(tp, cfg, obs)), (tp, obs)),
             "prefill_blk": lambda: (blk, (tp, obs, cand)),
             "zero_round": lambda: (dec, (params, obs, jnp.broadcast_to(ar(tp, obs)[:, None], cand.shape))),
             "random": lambda: (dec, (params, obs, cand))}
    return {name: calls[name]() for name in FUNCTIONS if name in names}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        sizes = [int(b) for b in FLAGS.batch_sizes]
        if min(sizes) < 1 or FLAGS.reps < 1 or FLAGS.trace_calls < 0:
            raise ValueError("batch sizes and --reps must be >= 1, --trace_calls >= 0")
        unknown = sorted(set(FLAGS.functions) - set(FUNCTIONS))
        if unknown or not FLAGS.functions:
            raise ValueError(f"--functions {unknown or '(none)'}: valid are {list(FUNCTIONS)}")
        trees = budget.parse_trees(FLAGS.tree) if FLAGS.tree else ()
        ((name, given),) = methods.parse_method_list(FLAGS.method)
        mcfg = methods.config(name, given)
        if not isinstance(mcfg.decode, hybrid.HybridConfig):
            raise ValueError(f"--method {name!r} is not a hybrid method")
    except ValueError as e:
        raise app.UsageError(f"{e} (--batch_sizes like 256,1024; --tree like 4x2x8; "
                             f"--method like heisd:budget=fixed)") from e
    tp, cfg, _, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    dp = checkpoint.load_drafter(FLAGS.drafter, cfg, tp)[0]
    cfg, tp, dp = methods.in_numerics(cfg, mcfg.numerics, tp, dp)
    hcfg = mcfg.decode
    if trees:
        hcfg = dataclasses.replace(hcfg, spec=budget.tree_spec(hcfg.spec, trees[0]))
    hcfg.check_fits(cfg)
    params = {"target": tp, "drafter": dp}
    print(f"{jax.devices()[0].device_kind}, {FLAGS.method}, tree {hcfg.spec.top_k}x{hcfg.spec.depth}x"
          f"{hcfg.spec.total_tokens}, verify={hcfg.verify}, {hcfg.n_verified} candidates", flush=True)
    results = []
    for batch in sizes:
        for name, (fn, args) in functions(params, cfg, hcfg, batch, FLAGS.functions).items():
            row = {"batch": batch, "name": name,
                   "ms": 1e3 * timing.median_seconds(lambda: fn(*args), FLAGS.reps)}
            if name in ("zero_round", "random"):
                row["rounds"] = float(jnp.max(fn(*args)[1]["rounds"]))
            if FLAGS.hlo_dir:
                timing.write_hlo(fn, args, Path(FLAGS.hlo_dir) / f"{name}_{batch}.hlo.txt.gz")
            if FLAGS.trace_calls:
                path = timing.trace_calls(lambda: fn(*args), FLAGS.trace_calls,
                                          Path(FLAGS.trace_dir) / f"{name}_{batch}")
                row["kernels"] = timing.kernel_summary(path, FLAGS.trace_calls, FLAGS.top) if path else {}
            results.append(row)
            rounds = f" ({row['rounds']:.0f} rounds)" if "rounds" in row else ""
            print(f"\nbatch {batch} {name}: {row['ms']:.3f} ms per call{rounds}", flush=True)
            for line, s in row.get("kernels", {}).items():
                print(f"  {line}: {s['total_ms']:.3f} ms per call")
                for kname, ms in s["top"]:
                    print(f"    {ms:9.3f}  {kname[:150]}")
        by = {r["name"]: r["ms"] for r in results if r["batch"] == batch}
        if {"zero_round", "prefill_blk", "ar"} <= set(by):
            print(f"\nbatch {batch}: zero-round decode {by['zero_round']:.2f} ms = prefill_blk {by['prefill_blk']:.2f} "
                  f"+ {by['zero_round'] - by['prefill_blk']:.2f} ms outside the target pass (AR {by['ar']:.2f} ms)",
                  flush=True)
        if FLAGS.out:
            results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()),
                                                     "method": FLAGS.method, "tree": FLAGS.tree, "rows": results})


if __name__ == "__main__":
    cli.run(main)
