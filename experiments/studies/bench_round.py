"""What one draft-verify round costs alone and inside the decode loop, in one run.

  python -m experiments.studies.bench_round --batch_sizes=1,16 --trees=4x2x8,8x4x32

With the shipped target and drafter and random observations, per batch size and tree (all
in-graph costs, `timing.in_graph_ms`: compiled once, median of back-to-back differences):
  alone      one `spec_decode.round_step` from the state after the prefill (whole state out)
  loop       `spec_decode.rounds` (the decode's `while_loop`) from that state, per round
  unrolled   the same number of rounds as a Python loop inside one jit, per round
The budget's cost table (heisd_jax/cost_model.py) reads the round's cost in context off
whole decodes because `loop` exceeds `alone`; this script shows by how much, and whether
the `while_loop` itself (its predicate) is the cause (`unrolled` vs `loop`).
"""

from __future__ import annotations

import jax
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import language
from heisd_jax import budget, checkpoint, cost_model, spec_decode as sd, timing, vla
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["1", "16"], "Batch sizes.")
cli.positive_int_list("batch_sizes")
flags.DEFINE_string("trees", "4x2x8", "Trees TOPKxDEPTHxTOTAL, separated by '/' or ','.")
flags.DEFINE_integer("reps", 7, "Back-to-back pairs per measurement (median).")
cli.define_paths("checkpoint", "drafter")


def measure(tp, dp, cfg: vla.VLAConfig, spec: sd.SpecConfig, batch: int, reps: int) -> dict:
    obs, _ = cost_model.synthetic_inputs(cfg, batch, 1)
    s0 = jax.jit(lambda tp, dp, obs: sd.start(tp, dp, cfg, *vla.prefill_features(tp, cfg, obs), obs,
                                              slack=spec.depth + 1))(tp, dp, obs)
    n = int(np.max(jax.jit(lambda tp, dp, s: sd.rounds(tp, dp, cfg, spec, s).stats["rounds"])(tp, dp, s0)))

    def unrolled(tp, dp, s):
        for _ in range(n):
            s = sd.round_step(tp, dp, cfg, spec, s)
        return s
    ms = lambda fn: timing.in_graph_ms(fn, (tp, dp, s0), reps=reps)  # noqa: E731
    return {"batch": batch, "rounds": n,
            "alone_ms": ms(lambda tp, dp, s: sd.round_step(tp, dp, cfg, spec, s)),
            "loop_ms": ms(lambda tp, dp, s: sd.rounds(tp, dp, cfg, spec, s)) / n,
            "unrolled_ms": ms(unrolled) / n}


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        specs = [budget.tree_spec(sd.SpecConfig(), t) for t in budget.parse_trees(FLAGS.trees.replace(",", "/"))]
        sizes = [int(b) for b in FLAGS.batch_sizes]
        if min(sizes) < 1:
            raise ValueError("batch sizes must be >= 1")
    except ValueError as e:
        raise app.UsageError(f"{e} (--trees like 4x2x8/8x4x32, --batch_sizes like 1,16)") from e
    tp, cfg, _, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    dp = checkpoint.load_drafter(FLAGS.drafter, cfg, tp)[0]
    for spec in specs:
        try:
            spec.check_fits(cfg)
        except ValueError as e:
            raise app.UsageError(str(e)) from e
    print(f"{jax.devices()[0].device_kind}, jax {jax.__version__}; ms per round", flush=True)
    for spec in specs:
        name = f"{spec.top_k}x{spec.depth}x{spec.total_tokens}"
        for b in sizes:
            r = measure(tp, dp, cfg, spec, b, FLAGS.reps)
            print(f"  tree {name:<8} B={b:<5} {r['rounds']} rounds: alone {r['alone_ms']:.3f}"
                  f"  loop {r['loop_ms']:.3f} ({r['loop_ms'] / r['alone_ms']:.2f}x)  unrolled {r['unrolled_ms']:.3f}",
                  flush=True)


if __name__ == "__main__":
    cli.run(main)
