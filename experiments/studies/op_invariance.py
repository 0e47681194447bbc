"""Which of the target's operations give a row the same result at every batch size and block length.

  python -m experiments.studies.op_invariance --batch=256 --out=results/op_invariance.json

A greedy decoder is batch-invariant only if each operation computes a row's output the same
way whatever else is in the batch: one state decoded alone must meet the same sums, in the
same order, as in a batch of 256. Strict speculative decoding needs the same along a pass's
tokens: a token verified in a block of T must get what AR's single-token pass gives it.
`target_confidence` measures the end result (the share of states whose actions agree); this
study finds the operations that break it, at the target's own shapes, on this device.

For each numerics (--numerics: `bfloat16`, everything in bf16, as the evaluator runs a bf16
checkpoint; `bf16_invariant`, the same with batch-invariant products and sums
(`heisd_jax.invariant_products`, `--matmul_precision=bf16_invariant`); `f32_act_bf16_products`, float32 activations with every matrix product on bf16
operands and float32 accumulation, `--dtype=float32 --matmul_precision=bf16`; `float32`), the
first row of --batch rows of random inputs is run within the batch and alone, through:
  - each operation of a decoder layer and the output head at the target's widths (random
    parameters), over blocks of T = 1, 8 (a draft tree) and the prompt's length of tokens, and
    the vision tower's patchify convolution and self-attention (over the image's patches);
  - a whole decoder layer over such a block (causal); with the shipped weights (random images
    and instructions), the prompt's embeddings (vision tower, text, proprio) and the prefill's
    logits of the last prompt token.
`batch`: the share of the row's output elements that differ; `batch_rel`: the largest
difference relative to the output's largest magnitude. For the per-token operations at T > 1,
`tokens` / `tokens_rel`: the same for the block's tokens run one at a time. A float32 output
differs in its last bits between kernels as a rule (harmless unless amplified: `_rel` is
~1e-7); a bf16 output that differs has rounded the other way (~4e-3 of the element).
"""

from __future__ import annotations

import os
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from experiments import cli
from heisd_jax import results_io, vla
from heisd_jax.harness import methods
from heisd_jax.observation import Observation

FLAGS = flags.FLAGS
cli.define_paths("checkpoint")
NUMERICS = {"bfloat16": ("bfloat16", "float32"), "f32_act_bf16_products": ("float32", "bf16"),
            "float32": ("float32", "float32"), "bf16_invariant": ("bfloat16", "bf16_invariant")}  # name -> (VLAConfig.dtype, VLAConfig.matmul_precision)
flags.DEFINE_list("numerics", list(NUMERICS), f"Numerics to test, of {list(NUMERICS)}.")
flags.DEFINE_integer("batch", 256, "Rows of the batch a row alone is compared against.")
flags.DEFINE_string("out", "results/op_invariance.json", "Results JSON.")


def operations(cfg: vla.VLAConfig):
    """name -> (per-token?, make(key, batch, t) -> (fn(*inputs), inputs)): the target's decoder
    operations at its widths in cfg's dtype, with random parameters and inputs."""
    d, h, dtype = cfg.d_model, cfg.n_heads, cfg.dtype
    hd = d // h
    normal = lambda key, shape: jax.random.normal(key, shape, jnp.float32).astype(dtype)  # noqa: E731

    def module(m, width):
        def make(key, b, t):
            kp, kx = jax.random.split(key)
            x = normal(kx, (b, t, width))
            params = m.init(kp, x[:1])
            return (lambda x: m.apply(params, x)), (x,)
        return make

    def scores(key, b, t):  # a block's queries against a cache of the prompt's keys
        kq, kk = jax.random.split(key)
        return (lambda q, k: jnp.einsum("bthd,bshd->bhts", q, k)), (normal(kq, (b, t, h, hd)),
                                                                    normal(kk, (b, cfg.prompt_len, h, hd)))

    def values(key, b, t):  # softmax weights against the cache's values
        ka, kv = jax.random.split(key)
        a = jax.nn.softmax(jax.random.normal(ka, (b, h, t, cfg.prompt_len)), -1).astype(dtype)
        return (lambda a, v: jnp.einsum("bhts,bshd->bthd", a, v)), (a, normal(kv, (b, cfg.prompt_len, h, hd)))

    def layer(key, b, t):  # a whole decoder layer over a causal block, no cache
        kp, kx = jax.random.split(key)
        x = normal(kx, (b, t, d))
        block = vla.DecoderBlock(cfg)
        mask = jnp.broadcast_to(vla.causal_mask(t, t)[None], (b, t, t))
        rotary = vla.rotary_angles(cfg, jnp.broadcast_to(jnp.arange(t), (b, t)))
        params = block.init(kp, x[:1], None, None, jax.tree.map(lambda r: r[:1], rotary), None, mask[:1])

        def fn(x):
            n = x.shape[0]
            return block.apply(params, x, None, None, jax.tree.map(lambda r: r[:n], rotary), None, mask[:n])[0]
        return fn, (x,)

    def patchify(key, b, t):  # the vision tower's first operation, on images (t unused)
        del t
        kp, kx = jax.random.split(key)
        x = jax.random.uniform(kx, (b, *cfg.image_shape), jnp.float32, -1, 1)
        m = nn.Conv(cfg.vision_width, (cfg.patch_size, cfg.patch_size), strides=cfg.patch_size, dtype=dtype)
        params = m.init(kp, x[:1])
        return (lambda x: m.apply(params, x)), (x,)

    def vision_attention(fp32_softmax: bool):
        def make(key, b, t):  # the vision tower's self-attention over the patches (t unused)
            del t
            kp, kx = jax.random.split(key)
            x = normal(kx, (b, cfg.n_patches, cfg.vision_width))
            m = nn.MultiHeadDotProductAttention(cfg.vision_heads, dtype=dtype, force_fp32_for_softmax=fp32_softmax)
            params = m.init(kp, x[:1], x[:1])
            return (lambda x: m.apply(params, x, x)), (x,)
        return make

    dense = lambda n: nn.Dense(n, use_bias=False, dtype=dtype)  # noqa: E731
    return {
        f"qkv {d}x{3 * d}": (True, module(dense(3 * d), d)),
        f"attn out {d}x{d}": (True, module(dense(d), d)),
        f"mlp gate/up {d}x{cfg.mlp_dim}": (True, module(dense(cfg.mlp_dim), d)),
        f"mlp down {cfg.mlp_dim}x{d}": (True, module(dense(d), cfg.mlp_dim)),
        f"head {d}x{cfg.vocab_size}": (True, module(dense(cfg.vocab_size), d)),
        "rmsnorm": (True, module(nn.RMSNorm(epsilon=cfg.norm_eps, dtype=dtype), d)),
        "attention q.k": (False, scores),
        "attention weights.v": (False, values),
        "decoder layer": (False, layer),
        "vision patchify (conv)": (False, patchify),
        "vision self-attention": (False, vision_attention(False)),
        "vision self-attention, f32 softmax": (False, vision_attention(True)),
    }


def difference(a, b) -> tuple[float, float]:
    """(share of elements that differ, largest difference / largest magnitude of a)."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    return float(np.mean(a != b)), float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(a))), 1e-30))


def _row(name, numerics, t, whole, alone, single=None) -> dict:
    row = {"numerics": numerics, "op": name, "t": t}
    row["batch"], row["batch_rel"] = difference(whole[:1], alone)
    if single is not None:
        row["tokens"], row["tokens_rel"] = difference(single, alone)
    print(f"{numerics:<22} {name:<26} T={t:<4} batch {row['batch']:.4f} ({row['batch_rel']:.1e})"
          + (f"  tokens {row['tokens']:.4f} ({row['tokens_rel']:.1e})" if single is not None else ""), flush=True)
    return row


def measure(cfg: vla.VLAConfig, params, numerics: str, batch: int) -> list[dict]:
    dtype, precision = NUMERICS[numerics]
    ncfg, nparams = methods.in_dtype(cfg, dtype, params, matmul_precision=precision)
    # Every function runs as the model's own passes do: at the config's matrix-product precision.
    at_precision = lambda fn: jax.jit(vla.at_config_precision(lambda _, c, *xs: fn(*xs)), static_argnums=1)  # noqa: E731
    rows = []
    for i, (name, (per_token, make)) in enumerate(operations(ncfg).items()):
        for t in (sorted({1, 8, cfg.prompt_len}) if not name.startswith("vision") else [cfg.n_patches]):
            fn, inputs = make(jax.random.PRNGKey(i), batch, t)
            run = at_precision(fn)
            whole, alone = run(None, ncfg, *inputs), run(None, ncfg, *(x[:1] for x in inputs))
            single = None
            if per_token and t > 1:  # each token of the first row in a pass of its own
                single = jnp.concatenate([run(None, ncfg, *(x[:1, j:j + 1] for x in inputs)) for j in range(t)], 1)
            rows.append(_row(name, numerics, t, whole, alone, single))
    k1, k2 = jax.random.split(jax.random.PRNGKey(len(rows)))
    obs = Observation(image=jax.random.randint(k1, (batch, *cfg.image_shape), 0, 256).astype(jnp.uint8),
                      instruction=jax.random.randint(k2, (batch, cfg.text_len), 1, cfg.text_vocab),
                      proprio=jax.random.normal(k2, (batch, cfg.proprio_dim)))
    embed = jax.jit(lambda p, o: vla.prompt_embeddings(p, ncfg, o))
    alone = embed(nparams, jax.tree.map(lambda x: x[:1], obs))
    rows.append(_row("prompt embeddings (shipped)", numerics, cfg.prompt_len, embed(nparams, obs), alone))
    prefill = jax.jit(lambda p, o: vla.prefill(p, ncfg, o)[0])
    alone = prefill(nparams, jax.tree.map(lambda x: x[:1], obs))
    rows.append(_row("prefill logits (shipped)", numerics, cfg.prompt_len, prefill(nparams, obs), alone))
    return rows


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    unknown = [n for n in FLAGS.numerics if n not in NUMERICS]
    if unknown:
        raise app.UsageError(f"--numerics {unknown}: valid are {', '.join(NUMERICS)}")
    if FLAGS.batch < 2:
        raise app.UsageError(f"--batch must be >= 2, got {FLAGS.batch}")
    params, cfg = cli.load_target(FLAGS.checkpoint)
    rows = [r for n in FLAGS.numerics for r in measure(cfg, params, n, FLAGS.batch)]
    Path(FLAGS.out).parent.mkdir(parents=True, exist_ok=True)
    results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "rows": rows})
    print(f"results: {os.path.abspath(FLAGS.out)}")


if __name__ == "__main__":
    cli.run(main)
