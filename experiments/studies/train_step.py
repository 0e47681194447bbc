"""Where one training step of the target VLA spends its time, on synthetic data of a build's shapes.

  python -m experiments.studies.train_step --out=train_step.json
  python -m experiments.studies.train_step --variants=default,forward --trace_dir=/tmp/train_trace

The step is `training.make_train_step` at `build_target`'s settings (the model of `--d_model`
and `--n_layers` on two 64-pixel views, minibatch 256, bf16 activations, 2-pixel random
shifts, deterministic compilation), drawing its minibatches from a device-resident step
table of `--table_steps` random steps (the contents do not change the step's cost). Each
variant is timed as the training loop runs it, `--steps` steps dispatched back to back and
waited for once (median ms per step over `--reps` such runs), so that the figure is the
device's time per step wherever the host keeps ahead of it:

  default           the step as `build_target` trains
  unpadded          the teacher-forced sequence at its own length (156 tokens) instead of
                    padded to `TrainConfig.seq_multiple` (160; the same loss)
  no_shift          without the random-shift augmentation
  nondeterministic  compiled without `xla_options.DETERMINISTIC`
  float32           float32 activations
  no_optimizer      the loss and its gradient, no AdamW update
  forward           the loss alone (minibatch draw included)
  draw              the minibatch draw alone (gather and shift)
  weighted          the default step on a table drawn by row weights (train --weights_from:
                    each row 1-4x, a binary search in their running sum per drawn row)
  draw_weighted     that table's minibatch draw alone

With `--trace_dir`, the default step is then traced for `--trace_calls` steps and summarised
per device timeline (`timing.kernel_summary`: ms and kernel count per step, the largest
kernels and how often each runs per step); `--hlo_dir` writes its update's optimised HLO beside
(the minibatch draw is a program of its own). Results are written after every variant, so a run cut short keeps what it measured.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from heisd_jax import results_io, timing, vla
from heisd_jax.harness import data, training
from heisd_jax.tokenizer import ActionTokenizer
from experiments import cli

FLAGS = flags.FLAGS
VARIANTS = ("default", "unpadded", "no_shift", "nondeterministic", "float32", "no_optimizer", "forward", "draw",
            "weighted", "draw_weighted")
flags.DEFINE_list("variants", list(VARIANTS), f"Variants to time, of {list(VARIANTS)}.")
flags.DEFINE_integer("batch_size", training.TrainConfig.batch_size, "Minibatch (build_target's default).")
flags.DEFINE_integer("d_model", vla.VLAConfig.d_model, "Decoder width (build_target's default).")
flags.DEFINE_integer("n_layers", vla.VLAConfig.n_layers, "Decoder layers (build_target's default).")
flags.DEFINE_integer("image_size", 64, "Each view's size in pixels (two views, as a build's --wrist data).")
flags.DEFINE_integer("table_steps", 20000, "Random steps in the device-resident step table.")
flags.DEFINE_integer("steps", 50, "Steps per timed run.")
flags.DEFINE_integer("reps", 3, "Timed runs per variant (median).")
flags.DEFINE_integer("trace_calls", 5, "Steps traced (with --trace_dir).")
flags.DEFINE_integer("top", 20, "Kernels listed per device timeline.")
flags.DEFINE_string("trace_dir", "", "Trace the default step here (empty: no trace).")
flags.DEFINE_string("hlo_dir", "", "Write the default step's optimised HLO here (train_step.hlo.txt.gz), where the "
                    "trace's kernel names can be looked up.")
flags.DEFINE_string("out", "results/train_step.json", "Results JSON.")


def synthetic_table(cfg: vla.VLAConfig, n: int, seed: int = 0) -> data.StepTable:
    """`n` random steps shaped as a dataset's for `cfg` (uint8 images, token ids, actions in [-1, 1])."""
    rng = np.random.default_rng(seed)
    return data.StepTable(image=rng.integers(0, 256, (n, *cfg.image_shape), dtype=np.uint8),
                          proprio=rng.standard_normal((n, cfg.proprio_dim)).astype(np.float32),
                          instruction=rng.integers(1, cfg.text_vocab, (n, cfg.text_len), dtype=np.int32),
                          action=rng.uniform(-1, 1, (n, 7)).astype(np.float32))


def variant_fn(name: str, model_cfg: vla.VLAConfig, cfg: training.TrainConfig, tok: ActionTokenizer):
    """(jitted fn(state, table, key) -> (state, out), the config it runs) for variant `name`."""
    run_cfg = dataclasses.replace(model_cfg, dtype="bfloat16")
    name = {"weighted": "default", "draw_weighted": "draw"}.get(name, name)  # the same step on a weighted table
    if name in ("default", "unpadded", "no_shift", "nondeterministic", "float32"):
        cfg = dataclasses.replace(cfg, image_shift=0 if name == "no_shift" else cfg.image_shift,
                                  deterministic=name != "nondeterministic",
                                  seq_multiple=1 if name == "unpadded" else cfg.seq_multiple)
        run_cfg = dataclasses.replace(run_cfg, dtype="float32") if name == "float32" else run_cfg
        return training.make_train_step(run_cfg, cfg, tok)

    def draw(table, key):
        return data.sample_batch(table, key, cfg.batch_size, tok, cfg.image_shift, model_cfg.n_views)

    def loss(params, table, key):
        obs, tokens = draw(table, key)
        return training.action_loss(params, run_cfg, obs, tokens, cfg.label_sigma_bins)

    def step(state, table, key):  # the state passes through, so runs chain as the loop's do
        key = jax.random.fold_in(key, state.step)
        if name == "draw":
            out = draw(table, key)
        elif name == "forward":
            out = loss(state.params, table, key)
        else:  # no_optimizer
            out = jax.grad(lambda p: loss(p, table, key)[0])(state.params)
        return state.replace(step=state.step + 1), out

    return training._jit(cfg)(step)


def ms_per_step(fn, state, table, key, steps: int, reps: int) -> float:
    """Median over `reps` runs of `steps` calls dispatched back to back, in ms per step."""
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(steps):
            state, out = fn(state, table, key)
        jax.block_until_ready((state, out))
        times.append((time.perf_counter() - t0) / steps * 1e3)
    return float(np.median(times))


def main(_):
    unknown = sorted(set(FLAGS.variants) - set(VARIANTS))
    if unknown:
        raise app.UsageError(f"--variants: unknown {unknown}; valid: {list(VARIANTS)}")
    model_cfg = vla.VLAConfig(image_size=FLAGS.image_size, n_views=2, d_model=FLAGS.d_model, n_layers=FLAGS.n_layers,
                              mlp_dim=vla.swiglu_width(FLAGS.d_model))
    cfg = training.TrainConfig(steps=10**6, batch_size=FLAGS.batch_size, warmup_steps=300, image_shift=2,
                               label_sigma_bins=0.6)
    host = synthetic_table(model_cfg, FLAGS.table_steps)
    tok = ActionTokenizer.fit(host.action, model_cfg.vocab_size)
    table, key = jax.device_put(host), jax.random.PRNGKey(0)
    # The same rows drawn by weights of 1-4 (as `data.load_step_table`'s task weights give).
    weighted = jax.device_put(data.with_row_weights(table, np.random.default_rng(1).integers(1, 5, table.size)))
    state = training.init_state(model_cfg, cfg)
    result = {**results_io.provenance(cli.command_line()), "batch_size": FLAGS.batch_size, "d_model": FLAGS.d_model,
              "n_layers": FLAGS.n_layers, "prompt_len": model_cfg.prompt_len, "table_steps": FLAGS.table_steps,
              "steps": FLAGS.steps, "reps": FLAGS.reps, "variants": {}}
    for name in FLAGS.variants:
        fn = variant_fn(name, model_cfg, cfg, tok)
        rows = weighted if name.endswith("weighted") else table
        t0 = time.perf_counter()
        jax.block_until_ready(fn(state, rows, key))  # compile and warm up
        compile_s = time.perf_counter() - t0
        ms = ms_per_step(fn, state, rows, key, FLAGS.steps, FLAGS.reps)
        result["variants"][name] = {"ms_per_step": round(ms, 3), "first_call_s": round(compile_s, 1)}
        print(f"{name:17s} {ms:8.3f} ms per step  (first call {compile_s:.1f} s)", flush=True)
        results_io.write_json_atomic(FLAGS.out, result)
    if FLAGS.trace_dir or FLAGS.hlo_dir:
        fn = variant_fn("default", model_cfg, cfg, tok)
        jax.block_until_ready(fn(state, table, key))
    if FLAGS.hlo_dir:
        # The update's program (the draw, a gather and a shift, is its own small program).
        result["hlo"] = str(timing.write_hlo(fn.update, (state, fn.settings, fn.draw(table, state.step, key)),
                                             f"{FLAGS.hlo_dir}/train_step.hlo.txt.gz"))
    if FLAGS.trace_dir:
        path = timing.trace_calls(lambda: fn(state, table, key), FLAGS.trace_calls, FLAGS.trace_dir)
        if path is not None:
            result["trace"] = {"file": str(path), "per_step": timing.kernel_summary(path, FLAGS.trace_calls, FLAGS.top)}
            for line, s in result["trace"]["per_step"].items():
                print(f"{line}: {s['total_ms']:.2f} ms, {s['count']:.0f} events per step")
                for kname, ms in s["top"][:10]:
                    print(f"  {ms:7.3f} ms  {s['launches'][kname]:6.1f} x  {kname[:100]}")
        results_io.write_json_atomic(FLAGS.out, result)
    print(f"results: {FLAGS.out}")


if __name__ == "__main__":
    cli.run(main)
