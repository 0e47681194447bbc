"""Which tile shape the batch-invariant product kernel should use on this device.

  python -m experiments.studies.invariant_tiles --tiles=64x64x32x4,64x64x64x4,128x128x32x4 --batch=512 \
      --out=results/invariant_tiles.json

`--matmul_precision=bf16_invariant` runs every product of the target with one kernel
configuration (`heisd_jax.invariant_products.Tiles`: output tile M x N, K block, warps,
pipeline stages). Any one configuration keeps a row's bits whatever the batch; they differ in
speed, and the best one is the device's answer, not the code's. For XLA's own bf16 numerics
(the baseline, in the same run) and for each configuration, with the shipped target's weights
on random observations: the prefill and one cached single-token pass (AR's step), at batch 1
and at --batch, each as its in-graph marginal cost (`timing.in_graph_ms`, what the cost tables
hold), and whether batch 1's logits equal row 0's in the batch, for both (every configuration
must give that; XLA's numerics do not on a GPU). Each configuration's logits are also compared
with the first configuration's (`same_bits_as_first`): where configurations that share a K
block give the same bits, a product's tile shape could follow its shape without breaking
invariance.

It also times the sums those numerics use (`invariant_products.pairwise_sum`) at the attention
softmax's shape [B, heads, prompt, prompt] for B = 1, 16 and --batch: the tree fused into one
kernel, its wide levels one kernel each, the same tree in one Pallas kernel
(`tree_sum_kernel`, on a GPU) and XLA's own (not invariant by construction) sum, and checks
that the trees give the same bits; and, with the first configuration, the whole numerics with
each other sum kind (`invariant_products.sum_kind`): "kernel" must keep the first's bits,
"xla" is invariant only as far as the check measures. A variant that fails to compile is
recorded as such; the JSON is written after each measurement.

Off a GPU the products run XLA's dot (the kernel needs one), so every configuration computes
alike there; the study is for GPUs.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from experiments import cli
from heisd_jax import invariant_products, results_io, timing, vla
from heisd_jax.harness import methods
from heisd_jax.observation import Observation

FLAGS = flags.FLAGS
cli.define_paths("checkpoint")
flags.DEFINE_list("tiles", ["64x64x32x4", "64x64x64x4", "128x128x32x4"],
                  "Kernel configurations, each MxNxK[xWARPS[xSTAGES]] of powers of two >= 16 (the defaults: the "
                  "fastest of nine on an H200 at batch 1 or 512, experiments/results/invariant_tiles_h200/).")
flags.DEFINE_integer("batch", 512, "The large batch (the evaluator's envs).")
flags.DEFINE_string("out", "results/invariant_tiles.json", "Results JSON.")


def random_obs(cfg: vla.VLAConfig, batch: int) -> Observation:
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    return Observation(image=jax.random.randint(k1, (batch, *cfg.image_shape), 0, 256).astype(jnp.uint8),
                       instruction=jax.random.randint(k2, (batch, cfg.text_len), 1, cfg.text_vocab),
                       proprio=jax.random.normal(k3, (batch, cfg.proprio_dim)))


def measure(cfg: vla.VLAConfig, params, obs: Observation, label: str) -> tuple[dict, tuple]:
    """The four pieces' ms and the two invariance checks, for cfg's numerics, traced now; and
    batch 1's (prefill, step) logits."""
    prefill = jax.jit(lambda p, o: vla.prefill(p, cfg, o))

    def step(p, cache, tok):
        b = tok.shape[0]
        return vla.cached_pass(p, cfg, cache, tok, jnp.zeros((b, 1), jnp.int32), jnp.ones((b, 1, 1), bool))[0]

    step = jax.jit(step)
    row = {"label": label}
    for name, o in (("1", jax.tree.map(lambda x: x[:1], obs)), ("batch", obs)):
        logits, _, cache = prefill(params, o)
        tok = (jnp.argmax(vla.action_logits(cfg, logits), -1) + cfg.first_action_id)[:, None]
        row[f"prefill_ms_{name}"] = timing.in_graph_ms(lambda p, o: vla.prefill(p, cfg, o)[0], (params, o))
        row[f"step_ms_{name}"] = timing.in_graph_ms(step, (params, cache, tok))
        row[f"_logits_{name}"] = (np.asarray(logits[:1]), np.asarray(step(params, cache, tok)[:1]))
    (p1, s1), (pb, sb) = row.pop("_logits_1"), row.pop("_logits_batch")
    row["prefill_invariant"], row["step_invariant"] = bool((p1 == pb).all()), bool((s1 == sb).all())
    print(f"{label:<22} prefill {row['prefill_ms_1']:.3f} / {row['prefill_ms_batch']:.3f} ms  "
          f"step {row['step_ms_1']:.3f} / {row['step_ms_batch']:.3f} ms  (batch 1 / {obs.image.shape[0]})  "
          f"invariant: prefill {row['prefill_invariant']}, step {row['step_invariant']}", flush=True)
    return row, (p1, s1)


def time_sums(cfg: vla.VLAConfig, batch: int) -> list[dict]:
    """The attention softmax's sum at batch 1, 16 and `batch`: the tree in one fusion, its wide
    levels apart, in one Pallas kernel (on a GPU) and XLA's own; whether the trees agree."""
    ways = {"fused": lambda v: invariant_products.pairwise_sum(v, (3,), level_kernels_above=1 << 62),
            "levels": lambda v: invariant_products.pairwise_sum(v, (3,), level_kernels_above=0),
            "xla": lambda v: jnp.sum(v, 3)}
    if jax.default_backend() == "gpu":
        ways["kernel"] = lambda v: invariant_products.tree_sum_kernel(v, (3,))
    rows = []
    for b in sorted({1, 16, batch}):
        shape = (b, cfg.n_heads, cfg.prompt_len, cfg.prompt_len)
        x = jax.random.uniform(jax.random.PRNGKey(b), shape, jnp.float32)
        row = {"shape": list(shape), **{f"{k}_ms": timing.in_graph_ms(f, (x,)) for k, f in ways.items()}}
        tree = np.asarray(jax.jit(ways["fused"])(x))
        row["trees_equal"] = all(bool((np.asarray(jax.jit(ways[k])(x)) == tree).all()) for k in ways if k != "xla")
        print(f"sum over {shape}: " + ", ".join(f"{k} {row[k + '_ms']:.3f} ms" for k in ways)
              + f"; the trees equal: {row['trees_equal']}", flush=True)
        rows.append(row)
    return rows


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        configs = [invariant_products.Tiles.parse(t) for t in FLAGS.tiles]
    except ValueError as e:
        raise app.UsageError(f"--tiles: {e}") from e
    if FLAGS.batch < 2:
        raise app.UsageError(f"--batch must be >= 2, got {FLAGS.batch}")
    params, cfg = cli.load_target(FLAGS.checkpoint)
    cfg, params = methods.in_dtype(cfg, "bfloat16", params)
    obs = random_obs(cfg, FLAGS.batch)
    result = {**results_io.provenance(cli.command_line()), "batch": FLAGS.batch, "rows": []}
    Path(FLAGS.out).parent.mkdir(parents=True, exist_ok=True)

    def add(row):  # written after each measurement: a later one that fails loses none before it
        result["rows"].append(row)
        results_io.write_json_atomic(FLAGS.out, result)

    result["sums"] = time_sums(cfg, FLAGS.batch)
    add(measure(cfg, params, obs, "xla bf16")[0])
    inv = dataclasses.replace(cfg, matmul_precision="bf16_invariant")
    variants = [(t, text, "pairwise") for t, text in zip(configs, FLAGS.tiles)]
    variants += [(configs[0], FLAGS.tiles[0], kind) for kind in invariant_products.SUMS if kind != "pairwise"]
    first = None
    for tiles, text, kind in variants:
        label = f"bf16_invariant {text}" + ("" if kind == "pairwise" else f", {kind} sums")
        try:  # read while each function is traced, inside
            with invariant_products.tile_shape(tiles), invariant_products.sum_kind(kind):
                row, logits = measure(inv, params, obs, label)
        except Exception as e:  # noqa: BLE001  (a candidate that does not compile is a result)
            print(f"{label}: failed: {type(e).__name__}: {str(e)[:500]}", flush=True)
            add({"label": label, "sums": kind, "error": f"{type(e).__name__}: {str(e)[:2000]}"})
            continue
        row.update(tiles=dataclasses.asdict(tiles), sums=kind)
        first = logits if first is None else first
        row["same_bits_as_first"] = all(bool((a == b).all()) for a, b in zip(logits, first))
        print(f"{'':<22} batch 1's logits equal to {FLAGS.tiles[0]}'s: {row['same_bits_as_first']}", flush=True)
        add(row)
    print(f"results: {os.path.abspath(FLAGS.out)}")


if __name__ == "__main__":
    cli.run(main)
