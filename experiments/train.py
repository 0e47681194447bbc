"""Trains the target VLA on collected demonstrations.

  python -m experiments.train --model=vla --demos=data/demos --out=runs/vla --steps=8000
  python -m experiments.train ... --export=checkpoints/vla     # also write the shippable policy
  python -m experiments.train --demos=data/demos,data/dagger1 --init=runs/vla0.policy ...  # DAgger

--demos takes several datasets (expert demonstrations first, then DAgger aggregates): their
training episodes are pooled; the validation steps are the held-out episodes of the first.
The model's image size and number of camera views are read from the data. --init starts
from a policy checkpoint's parameters and tokenizer (fresh optimizer and schedule).

--weights_from=DAGGER_DATASET (or an evaluation's results JSON) draws each step in proportion
to how often that policy failed its task (`envs.tasks.failure_weights`, up to 4x; others 1):
a round's fine-tuning then weighs what its policy gets wrong, not the aggregate's task mix.

--demo_weights=1,1,3 draws each step of the third dataset three times as often as the others'
(a round's newest data against the aggregate); the share of the draws each dataset gets is printed.

--devices=N trains data parallel over N local devices (0: all): the state and the step
table are replicated on each, every minibatch is split over them (`heisd_jax.harness.training`).

Training state is checkpointed with orbax under --out/state every --ckpt_every steps; a
rerun with the same --out resumes from the latest one. Loss and per-dimension token
accuracy are printed and appended to --out/log.jsonl. The last line splits the stage's wall
time, from the process's imports to the export (`time: ...`; build_target records it).
"""

from __future__ import annotations

import dataclasses
import json
import time

T_START = time.perf_counter()  # the time split counts the imports below (JAX, MuJoCo)

from pathlib import Path

import jax
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import demos, language, tasks as tasks_lib
from heisd_jax import checkpoint, sharding, vla
from heisd_jax.harness import data, training, vla_policy
from heisd_jax.timing import Phases
from heisd_jax.tokenizer import ActionTokenizer
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_enum("model", "vla", ["vla", "drafter"], "What to train: the target VLA, or an EAGLE drafter for the "
                  "target of --target (frozen).")
flags.DEFINE_string("target", str(vla_policy.DEFAULT_CHECKPOINT), "--model=drafter: the target VLA checkpoint.")
cli.existing_dir("target", "policy checkpoint")
flags.DEFINE_list("demos", ["data/demos"], "Demonstration datasets (experiments.collect_demos), comma-separated; "
                  "validation uses the held-out episodes of the first.")
flags.DEFINE_string("weights_from", "", "A DAgger dataset (collect_demos --policy) or an evaluation's results JSON: "
                    "each training step is drawn in proportion to how often that policy failed its task "
                    "(envs.tasks.failure_weights: 1 + 10 x failure rate, up to 4x; other tasks 1). Empty: uniform.")
flags.DEFINE_list("demo_weights", [], "One positive integer per --demos dataset: each of its steps is drawn that many "
                  "times as often (on top of --weights_from's task weights), e.g. 1,1,3,3 draws the last two datasets' "
                  "steps three times as often as the first two's. Empty: every dataset 1.")
flags.DEFINE_string("init", "", "--model=vla: start from this policy checkpoint's parameters and tokenizer.")
cli.existing_dir("init", "policy checkpoint")
flags.DEFINE_enum("compute_dtype", "bfloat16", ["float32", "bfloat16"], "Activation dtype while training (parameters "
                  "and optimizer state stay float32; the exported policy computes in float32).")
flags.DEFINE_string("out", "runs/vla", "Run directory (training state, log).")
flags.DEFINE_string("export", "", "If set, write the final parameters as a policy checkpoint here.")
flags.DEFINE_enum("export_param_dtype", "float32", list(checkpoint.PARAM_DTYPES), "--model=vla: the dtype the exported "
                  "policy's parameters are stored in (bfloat16: half the file; loaded back in bfloat16).")
flags.DEFINE_integer("steps", 8000, "Optimizer steps.")
flags.DEFINE_integer("batch_size", 256, "Minibatch size.")
flags.DEFINE_float("lr", 3e-4, "Peak learning rate.")
flags.DEFINE_integer("warmup_steps", 500, "Linear warm-up steps.")
flags.DEFINE_float("holdout", 0.05, "Fraction of episodes held out for validation.")
flags.DEFINE_float("label_sigma_bins", 0.0, "Ordinal label smoothing: Gaussian targets of this std in bins (0: one-hot).")
flags.DEFINE_integer("seq_multiple", training.TrainConfig.seq_multiple, "--model=vla: pad the teacher-forced "
                     "sequence to a multiple of this (the same loss; 1: no padding), for aligned kernels.")
flags.DEFINE_integer("image_shift", 0, "Random-shift image augmentation, pixels (0: off).")
flags.DEFINE_integer("log_every", 200, "Steps between log lines.")
flags.DEFINE_integer("ckpt_every", 2000, "Steps between training-state checkpoints.")
flags.DEFINE_integer("d_model", vla.VLAConfig.d_model, "Decoder width.")
flags.DEFINE_integer("n_layers", vla.VLAConfig.n_layers, "Decoder layers.")
flags.DEFINE_integer("patch_size", vla.VLAConfig.patch_size, "ViT patch size.")
flags.DEFINE_integer("devices", 1, "Local devices to train over, data parallel (0: all of them); --batch_size must "
                     "be a multiple.")
flags.DEFINE_integer("seed", 0, "Fixes the initialisation and the minibatch order: the same seed and data give the "
                     "same run (on a GPU with --deterministic).")
flags.DEFINE_bool("deterministic", True, "Compile the training step with deterministic GPU reductions and "
                  "convolutions (heisd_jax.xla_options.DETERMINISTIC), so a rerun gives the same parameters.")
flags.DEFINE_float("time_budget_s", 0, "If > 0, stop (checkpoint and export) after this many seconds of training.")


PHASES = Phases(mark=T_START)  # the stage's wall time in named phases, from the process's imports


def _loop(out: Path, mngr, state, meta: dict, cfg, step_fn, record_fn):
    """Optimizer steps with logging, periodic checkpoints and the time budget; resumable. The
    steps run asynchronously; the loop waits for them only where it logs, saves or ends, so
    `PHASES` counts their device time under "steps" (the first, with its compile, apart)."""
    t0, log = time.perf_counter(), open(out / "log.jsonl", "a")
    key = jax.random.PRNGKey(cfg.seed + 1)
    s = first = int(state.step)  # counted on the host: reading state.step would wait for every step
    PHASES.lap("setup")
    while s < cfg.steps:
        state, m = step_fn(state, key)
        s += 1
        if s == first + 1:  # the first step waits for its programs' compile (or cache load)
            jax.block_until_ready(m)
            PHASES.lap("first step")
        out_of_time = FLAGS.time_budget_s > 0 and time.perf_counter() - t0 > FLAGS.time_budget_s
        if s % FLAGS.log_every == 0 or s == cfg.steps or out_of_time:
            jax.block_until_ready(m)
            PHASES.lap("steps")
            rec = {"step": s, **record_fn(state, m, s), "elapsed_s": round(time.perf_counter() - t0, 1)}
            print(json.dumps(rec), flush=True)
            log.write(json.dumps(rec) + "\n")
            log.flush()
            PHASES.lap("held-out evaluation")
        if s % FLAGS.ckpt_every == 0 or s == cfg.steps or out_of_time:
            checkpoint.save(mngr, s, state, meta)
            PHASES.lap("checkpoints")
        if out_of_time:
            print(f"time budget spent: stopping at step {s} of {cfg.steps}")
            break
    PHASES.lap("steps")
    PHASES.notes["steps"] = f"{max(s - first - 1, 0)} after the first"
    return state


def _demo_weights() -> list[int]:
    """--demo_weights as integers, one per --demos dataset (all 1 where not given); UsageError
    naming the flag otherwise."""
    if not FLAGS.demo_weights:
        return [1] * len(FLAGS.demos)
    text = ",".join(FLAGS.demo_weights)
    if len(FLAGS.demo_weights) != len(FLAGS.demos) or not all(v.strip().isdigit() and int(v) >= 1
                                                              for v in FLAGS.demo_weights):
        raise app.UsageError(f"--demo_weights: expected one positive integer per --demos dataset "
                             f"({len(FLAGS.demos)}), got {text}")
    return [int(v) for v in FLAGS.demo_weights]


def _tables(draw: dict):
    """(train, validation) step tables on the host, and the (image size, views) of the data:
    the training episodes of every --demos dataset in one table, drawn by `draw`'s task and
    dataset weights (`data.load_step_table`), the first dataset's held-out episodes (its
    training episodes where it holds none out) for validation, drawn uniformly."""
    splits = [data.random_episode_split(path, FLAGS.holdout) for path in FLAGS.demos]
    t0 = time.perf_counter()
    try:
        host = data.load_step_table([(path, train_eps) for path, (train_eps, _) in zip(FLAGS.demos, splits)],
                                    draw["task_weights"], draw["demo_weights"])
    except ValueError as e:
        raise app.UsageError(f"--demos: {e}") from e
    row = 0
    for path, (train_eps, val_eps) in zip(FLAGS.demos, splits):
        ds = demos.DemoDataset(path)
        rows = sum(ds.episodes[i]["length"] for i in train_eps)
        share = data.draw_share(host, slice(row, row + rows))
        print(f"{path}: {len(train_eps)} training episodes ({rows} steps, {100 * share:.1f}% of the draws), "
              f"{len(val_eps)} held out")
        row += rows
    first_train, first_val = splits[0]
    val_host = data.load_steps(FLAGS.demos[0], first_val or first_train)
    print(f"loaded {host.size} training and {val_host.size} held-out steps in {time.perf_counter() - t0:.1f}s")
    PHASES.lap("load")
    if draw["task_weights"]:
        print(f"steps drawn by their task's failure weight: {draw['task_weights']}")
    h, w, _ = host.image.shape[1:]
    if w % h:
        raise app.UsageError(f"images of {h}x{w} are not square views tiled side by side")
    n = sharding.local_mesh(FLAGS.devices).size
    print(f"{n} x {jax.devices()[0].device_kind}{', data parallel' if n > 1 else ''}")
    return host, val_host, h, w // h


def _mesh():
    """The mesh of --devices local devices, or None for one device (plain jit)."""
    mesh = sharding.local_mesh(FLAGS.devices)
    return mesh if mesh.size > 1 else None


def _place(mesh, tree):
    """`tree` on the device (one device) or replicated over the mesh."""
    return jax.device_put(tree) if mesh is None else sharding.replicate(mesh, tree)


def _placed(*trees):
    """`trees` once their copies to the devices are complete, the wait timed as the phase
    "table placed" (the first step would wait for them anyway): a large aggregate's copy
    would otherwise hide in the setup's or the first step's seconds."""
    jax.block_until_ready(trees)
    PHASES.lap("table placed")
    return trees


def _first(tree):
    """A replicated tree's copy on the first device (for the single-device evaluation)."""
    return jax.device_put(tree, jax.local_devices()[0])


def train_vla(out: Path, cfg: training.TrainConfig, draw: dict):
    host, val_host, image_size, n_views = _tables(draw)
    init = None
    if FLAGS.init:
        try:
            init = checkpoint.load_policy(FLAGS.init, text_vocab=language.VOCAB)
        except ValueError as e:
            raise app.UsageError(str(e)) from e
        model_cfg = dataclasses.replace(init[1], dtype="float32")
        if model_cfg.image_shape != host.image.shape[1:]:
            raise app.UsageError(f"--init {FLAGS.init} takes images {model_cfg.image_shape}, the demos hold "
                                 f"{host.image.shape[1:]}")
    else:
        model_cfg = vla.VLAConfig(image_size=image_size, n_views=n_views, patch_size=FLAGS.patch_size,
                                  d_model=FLAGS.d_model, n_layers=FLAGS.n_layers,
                                  mlp_dim=vla.swiglu_width(FLAGS.d_model))
    mngr = checkpoint.manager(out / "state")
    tok = init[2] if init is not None else ActionTokenizer.fit(np.asarray(host.action), model_cfg.vocab_size)
    if mngr.latest_step() is None:
        state = (training.continue_from(model_cfg, cfg, init[0]) if init is not None
                 else training.init_state(model_cfg, cfg))
    else:
        state, meta = checkpoint.restore(mngr, jax.eval_shape(lambda: training.init_state(model_cfg, cfg)))
        if meta["config"] != dataclasses.asdict(model_cfg):
            raise app.UsageError(f"{out} holds a run with another model config; use another --out")
        tok = ActionTokenizer.from_dict(meta["tokenizer"])
        print(f"resumed from step {int(state.step)}")
    n_params = sum(x.size for x in jax.tree.leaves(state.params))
    print(f"VLA {n_params / 1e6:.2f}M parameters, prompt {model_cfg.prompt_len} tokens")
    PHASES.lap("state")
    mesh = _mesh()
    table, val_table, state = _placed(_place(mesh, host), jax.device_put(val_host), _place(mesh, state))
    run_cfg = dataclasses.replace(model_cfg, dtype=FLAGS.compute_dtype)
    step = training.make_train_step(run_cfg, cfg, tok, mesh)
    eval_fn = training.make_eval_fn(model_cfg, tok, min(1024, val_table.size), cfg)
    eval_key = jax.random.PRNGKey(cfg.seed + 2)

    def record(state, m, s):
        vloss, vm = eval_fn(_first(state.params), val_table, jax.random.fold_in(eval_key, s))
        return {"loss": float(m["loss"]), "token_acc": float(m["token_acc"].mean()), "val_loss": float(vloss),
                "val_token_acc": [round(float(a), 4) for a in vm["token_acc"]],
                "val_bin_err": [round(float(a), 2) for a in vm["bin_err"]],
                "val_decisive": [round(float(a), 4) for a in vm["decisive"]]}

    meta = checkpoint.metadata(model_cfg, tok, extra={"train": dataclasses.asdict(cfg), "demos": list(FLAGS.demos),
                                                      **draw, "init": FLAGS.init,
                                                      "compute_dtype": FLAGS.compute_dtype},
                               text_vocab=language.VOCAB)
    state = _loop(out, mngr, state, meta, cfg, lambda st, k: step(st, table, k), record)
    if FLAGS.export:
        checkpoint.save_policy(FLAGS.export, _first(state.params), model_cfg, tok,
                               extra={k: meta[k] for k in ("train", "demos", "task_weights", "demo_weights", "init",
                                                           "compute_dtype")},
                               text_vocab=language.VOCAB, param_dtype=FLAGS.export_param_dtype)
        print(f"policy checkpoint: {FLAGS.export}")
        PHASES.lap("export")


def train_drafter(out: Path, cfg: training.TrainConfig, draw: dict):
    tparams, model_cfg, _, _ = checkpoint.load_policy(FLAGS.target, text_vocab=language.VOCAB)
    host, val_host, _, _ = _tables(draw)
    if host.image.shape[1:] != model_cfg.image_shape:
        raise app.UsageError(f"the target takes images {model_cfg.image_shape}, the demos hold {host.image.shape[1:]}")
    table, val_table = jax.device_put(host), jax.device_put(val_host)
    t0 = time.perf_counter()
    tokens, val_tokens = (training.greedy_tokens(tparams, model_cfg, t) for t in (table, val_table))
    print(f"target greedy tokens of {table.size + val_table.size} steps in {time.perf_counter() - t0:.1f}s")
    PHASES.lap("target tokens")
    fp = checkpoint.fingerprint(tparams)
    mngr = checkpoint.manager(out / "state")
    state = training.init_drafter_state(model_cfg, cfg)
    meta = {"format": checkpoint.FORMAT, "kind": "drafter_run", "config": dataclasses.asdict(model_cfg),
            "target_fingerprint": fp, "train": dataclasses.asdict(cfg), "demos": list(FLAGS.demos),
            **draw}
    if mngr.latest_step() is not None:
        state, old = checkpoint.restore(mngr, jax.eval_shape(lambda: state))
        if old.get("target_fingerprint") != fp:
            raise app.UsageError(f"{out} holds a drafter run for another target; use another --out")
        print(f"resumed from step {int(state.step)}")
    print(f"drafter {sum(x.size for x in jax.tree.leaves(state.params)) / 1e6:.2f}M parameters, target {fp}")
    PHASES.lap("state")
    mesh = _mesh()
    state, table_m, tparams_m, tokens_m = _placed(*(_place(mesh, x) for x in (state, table, tparams, tokens)))
    step = training.make_drafter_step(model_cfg, cfg, mesh)
    eval_fn = training.make_drafter_eval(model_cfg, min(1024, val_table.size), cfg)
    eval_key = jax.random.PRNGKey(cfg.seed + 2)

    def record(state, m, s):
        vloss, vm = eval_fn(_first(state.params), tparams, val_table, val_tokens, jax.random.fold_in(eval_key, s))
        return {"loss": float(m["loss"]), "reg": float(m["reg"]), "ce": float(m["ce"]), "val_loss": float(vloss),
                "val_top1": [round(float(a), 4) for a in vm["top1"]]}

    state = _loop(out, mngr, state, meta, cfg, lambda st, k: step(st, tparams_m, table_m, tokens_m, k), record)
    if FLAGS.export:
        checkpoint.save_drafter(FLAGS.export, state.params, model_cfg, tparams, extra={"train": meta["train"]})
        print(f"drafter checkpoint: {FLAGS.export}")
        PHASES.lap("export")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    out = Path(FLAGS.out)
    try:
        task_weights = tasks_lib.parse_suite_weights(cli.failure_weights(FLAGS.weights_from)) if FLAGS.weights_from else {}
        for path in FLAGS.demos:
            demos.DemoDataset(path)
        draw = {"task_weights": task_weights, "demo_weights": _demo_weights()}  # how the steps are drawn
        for name in ("init",) if FLAGS.model == "vla" else ("target",):
            path = getattr(FLAGS, name)
            if path and not Path(path).is_dir():
                raise FileNotFoundError(f"--{name} {path}: no checkpoint there")
        n = sharding.local_mesh(FLAGS.devices).size
        if FLAGS.batch_size % n:
            raise ValueError(f"--batch_size={FLAGS.batch_size} cannot be split evenly over {n} devices; use a "
                             f"multiple of {n}")
        cfg = training.TrainConfig(steps=FLAGS.steps, batch_size=FLAGS.batch_size, lr=FLAGS.lr,
                                warmup_steps=FLAGS.warmup_steps, label_sigma_bins=FLAGS.label_sigma_bins,
                                image_shift=FLAGS.image_shift, seed=FLAGS.seed,
                                deterministic=FLAGS.deterministic, seq_multiple=FLAGS.seq_multiple)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    out.mkdir(parents=True, exist_ok=True)
    PHASES.lap("start")
    (train_vla if FLAGS.model == "vla" else train_drafter)(out, cfg, draw)
    print(PHASES.line())


if __name__ == "__main__":
    cli.run(main)
