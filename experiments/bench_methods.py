"""Per-action decoding speed of every method on the same closed-loop trajectories, in one run.

  python -m experiments.bench_methods --suites=goal --batch_sizes=1,256 \
      --methods="ar;drafter:acceptance=token_relaxed,relax_bins=9;heisd" --out=results/bench_methods.json

Closed-loop timings mix decoding with physics and rendering, and at batch 1 MJX's substeps
dominate. To time the decoder alone on realistic inputs, this first records --steps control
steps of --record_method (default ar) in --record_envs envs on the fixed evaluation initial
states (images, proprio, end-effector kinematics as the rollout saw them), then, per method
and batch size B, replays them: a jitted `lax.scan` over replay steps calls the method's
policy step (its own state carried: action history, boundary, skips, the draft budget's
estimates) on B lanes. Only running steps are replayed (`envs.rollout.replay_lanes`): lane
j plays the running steps of recorded envs j, j + B, j + 2B, ... (--lane_envs of them, fewer
where the recording has fewer than B x --lane_envs) back to back, its per-env state reset
where an episode starts (the batch-wide draft budget carries on), as an evaluator's refilled
env slot does; every lane is cut to the shortest. (A finished episode's frozen observation
repeats its last action, which a method with verify-skip decodes almost for free: replaying
those steps would credit it with time no running env saves.) Compiled ahead, then timed over --reps
calls after an untimed first one; a first call of `LONG_RUN_S` or more counts as the first repetition
(one-time costs of a first run are far below 0.1 % of it, and a whole-episode replay of a 7B-scale
target runs ~80 s a call); the actions and stats are the last call's. Median of the repetitions;
speedup = AR time / method time in this run, with its spread
(min..max of the per-repetition ratios, AR's i-th repetition against the method's i-th).
The target's prefill alone is timed the same way: AR / prefill is the ceiling of any method
that prefills every action, reported per batch size. Per method it also reports target passes per
action (TPA), tokens per target pass (AL), the mode shares, and how often the method's
action equals AR's in this replay at the same batch size (`=AR`, `identical_to_ar_replay`:
strict methods 1.0) and the recorded action (`=rec`, `identical_to_ar`, with the mean bin
distance): AR replayed at another batch size than the recording's gives the recorded action only
as far as the target is batch-invariant (float32: always; bfloat16: not, docs/target.md).
The replay is open loop: the observations are the recording method's, so a method's own
drift (and its success rate) is not captured: see experiments.sweep for that.
--device_loops compiles every replay with `heisd_jax.xla_options.DEVICE_LOOPS` (what the
public decode call and experiments.profile compile a host loop's decode step with).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from envs import language, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax.timing import median_seconds, repeated
from heisd_jax.tokenizer import N_BINS
from heisd_jax import checkpoint, results_io, retrieval, scale, vla, xla_options
from heisd_jax.harness import methods, replay, vla_policy
from experiments import cli

FLAGS = flags.FLAGS
LONG_RUN_S = 20.0  # a first call at least this long is timed as a repetition (see above)
cli.define_cost_flags()
flags.DEFINE_string("methods", "ar;drafter:acceptance=token_relaxed,relax_bins=9;heisd",
                    "Methods (as in experiments.sweep); AR is always timed first as the baseline.")
flags.DEFINE_string("suites", "goal", f"Suites of {list(tasks_lib.SUITES)} or 'all'.")
flags.DEFINE_list("batch_sizes", ["1", "256"], "Batch sizes.")
cli.positive_int_list("batch_sizes")
flags.DEFINE_integer("record_envs", 256, "Recorded envs (>= the largest batch size).")
flags.DEFINE_integer("steps", 120, "Recorded control steps per env.")
flags.DEFINE_enum("record_method", "ar", ["ar", "expert"], "Policy whose rollouts are recorded.")
flags.DEFINE_integer("lane_envs", 4, "Recorded envs each replayed row plays one after another (their running steps).")
flags.DEFINE_integer("reps", 5, "Timed calls per measurement (median).", lower_bound=1)
cli.define_paths("checkpoint", "drafter", "datastore")
flags.DEFINE_enum("target_scale", None, list(scale.SCALE_NAMES), "Every timed method (and the ceiling) with the "
                  "target expanded to this architecture (docs/scale.md), unless its --methods settings name one; "
                  "the recording runs the shipped target, whose tokens are the same.")
flags.DEFINE_enum("dtype", None, list(methods.DTYPES), "Every timed method (and the ceiling) in this dtype, unless its "
                  "--methods settings name one.")
flags.DEFINE_enum("matmul_precision", None, list(vla.MATMUL_PRECISIONS), "Every timed method (and the ceiling) at "
                  "this matrix-product precision, unless its --methods settings name one (bf16_invariant: `=AR` "
                  "then says whether strict methods are token-identical to AR in bf16).")
flags.DEFINE_enum("attention", None, [vla.AUTO_ATTENTION, *vla.ATTENTIONS], "Every timed method (and the ceiling) "
                  "with this prefill attention, unless its --methods settings name one (default: each method's, "
                  "auto: cuDNN's for an expanded target on a GPU in 16 bits).")
flags.DEFINE_enum("patchify", None, list(vla.PATCHIFIES), "Every timed method (and the ceiling) with the vision "
                  "tower's patchify as a convolution or one matrix product (vla.Patchify), unless its --methods "
                  "settings name one (default: conv).")
flags.DEFINE_bool("ceiling", True, "Also time the prefill alone (the AR / prefill ceiling).")
flags.DEFINE_bool("device_loops", False, "Compile every replay (AR's, the ceiling's and each method's) with "
                  "heisd_jax.xla_options.DEVICE_LOOPS: on a GPU the replay's step loop, the draft rounds and the "
                  "budget's branches run as device-side graph nodes (the replay holds no physics).")
flags.DEFINE_string("out", "", "JSON output path.")
flags.DEFINE_string("plot", "", "PNG: speedup over AR vs batch size per method, with the ceiling (needs matplotlib).")
flags.DEFINE_list("replot", [], "Instead of measuring: plot the rows of these --out JSON files (e.g. two runs of "
                  "other batch sizes) into --plot.")


def common_settings() -> dict:
    """The settings --target_scale, --dtype, --matmul_precision, --attention and --patchify give every
    timed method."""
    return {k: FLAGS[k].value for k in ("target_scale", "dtype", "matmul_precision", "attention", "patchify")
            if FLAGS[k].value is not None}


def prefill_policy(env: TabletopEnv):
    """The target's prefill alone (its greedy first token repeated): the floor of any method
    that prefills every action."""
    params, cfg, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    cfg, params = methods.in_numerics(cfg, methods.config("ar", common_settings()).numerics, params)

    def decode(params, cfg, obs):
        logits, _, _ = vla.prefill(params, cfg, obs)
        first = jnp.argmax(vla.action_logits(cfg, logits), -1) + cfg.first_action_id
        b = first.shape[0]
        return jnp.repeat(first[:, None], 7, 1), {"target_passes": jnp.ones((b,), jnp.float32)}
    return vla_policy.decoding_policy("prefill", params, cfg, tok, decode)


def plot(rows, path):
    import matplotlib  # noqa: PLC0415
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    fig, ax = plt.subplots(figsize=(6.5, 4))
    labels = sorted({r["label"] for r in rows}, key=[r["label"] for r in rows].index)
    for label in labels:
        rs = sorted((r for r in rows if r["label"] == label), key=lambda r: r["batch"])
        b = [r["batch"] for r in rs]
        y = [r["speedup_vs_ar"] for r in rs]
        err = [[r["speedup_vs_ar"] - r["speedup_spread"][0] for r in rs],
               [r["speedup_spread"][1] - r["speedup_vs_ar"] for r in rs]]
        style = dict(ls="--", color="k") if label == "prefill" else {}
        ax.errorbar(b, y, yerr=err, marker="o", capsize=3, label="ceiling (AR / prefill)" if label == "prefill" else label,
                    **style)
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("batch size (envs)")
    ax.set_ylabel("speedup over AR (same run)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    if FLAGS.replot:
        if not FLAGS.plot:
            raise app.UsageError("--replot needs --plot (the PNG to write)")
        missing = [f for f in FLAGS.replot if not Path(f).is_file()]
        if missing:
            raise app.UsageError(f"--replot: no such file(s): {missing}")
        plot([r for f in FLAGS.replot for r in json.loads(Path(f).read_text())["rows"]], FLAGS.plot)
        return
    try:
        method_list = methods.parse_method_list(FLAGS.methods)
        task_list = tasks_lib.get_tasks(FLAGS.suites)
        sizes = sorted({int(b) for b in FLAGS.batch_sizes})
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if FLAGS.lane_envs < 1:
        raise app.UsageError(f"--lane_envs must be >= 1, got {FLAGS.lane_envs}")
    if sizes[0] < 1 or sizes[-1] > FLAGS.record_envs:
        raise app.UsageError(f"batch sizes must be in 1..--record_envs={FLAGS.record_envs}, got {sizes}")
    common = common_settings()
    method_list = [(n, {**common, **s}) for n, s in [("ar", {})] + [m for m in method_list if m != ("ar", {})]]
    cli.check_methods(method_list, sizes, FLAGS.checkpoint, FLAGS.datastore)  # now, not after the recording
    env = TabletopEnv(task_list, methods.env_config("ar", FLAGS.checkpoint))
    t0 = time.perf_counter()
    states, ar_actions, done = replay.record(env, methods.make_policy(FLAGS.record_method, env,
                                                                      checkpoint=FLAGS.checkpoint),
                                             FLAGS.record_envs, FLAGS.steps)
    print(f"recorded {FLAGS.record_envs} envs x {FLAGS.steps} steps of {FLAGS.record_method} in "
          f"{time.perf_counter() - t0:.0f}s (compile included) on {jax.devices()[0].device_kind}", flush=True)
    _, _, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
    running = ~np.asarray(done)
    rows, query_ms = [], {}
    store_path = Path(FLAGS.datastore)
    if any(n in ("retrieval", "heisd") for n, _ in method_list) and store_path.exists():
        params, _, tok, _ = checkpoint.load_policy(FLAGS.checkpoint, text_vocab=language.VOCAB)
        store, key_spec, _ = retrieval.load(store_path, tok, checkpoint.fingerprint(params))
        for b in sizes:  # the kNN query alone (it must stay far below one target pass)
            keys = jnp.zeros((b, key_spec.dim), jnp.float32)
            q = jax.jit(lambda s, k: retrieval.query(s, k, jnp.zeros((b,), jnp.int32), 4))
            query_ms[b] = 1e3 * median_seconds(lambda: q(store, keys), max(FLAGS.reps, 10))
            print(f"B={b:<4} retrieval query ({store.size} entries): {query_ms[b]:.3f} ms", flush=True)
    for b in sizes:
        t_idx, e_idx = rollout.replay_lanes(running, min(FLAGS.record_envs, b * FLAGS.lane_envs), b)
        sub = jax.tree.map(lambda x: x[t_idx, e_idx], states)
        ar_bins = np.asarray(tok.to_bins(np.asarray(ar_actions)[t_idx, e_idx]))
        print(f"B={b:<4} replay: {t_idx.shape[0]} running steps per lane", flush=True)
        base = None
        todo = list(method_list) + ([("prefill", {})] if FLAGS.ceiling else [])
        for name, settings in todo:
            # The last method's weights, executable and outputs go before the next is built: at 7B
            # and batch 256 two methods' buffers do not fit on one GPU together.
            policy = fn = compiled = out = None
            t_build = time.perf_counter()
            if name == "prefill":
                policy = prefill_policy(env)
            else:
                try:
                    policy = methods.make_policy(name, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                                 datastore=FLAGS.datastore, batch_size=b,
                                                 **cli.cost_kwargs(), **settings)
                except (ValueError, FileNotFoundError) as e:
                    if FLAGS.out and rows:
                        write(rows, query_ms)  # what was measured stays
                    raise app.UsageError(f"{name} at batch {b}: {e}") from e
            if policy.meta.get("cost_table") is not None:
                print(policy.meta["cost_table"].report(), flush=True)
            fn = replay.replay_fn(policy, xla_options.DEVICE_LOOPS if FLAGS.device_loops else None)
            t_built = time.perf_counter()
            compiled = fn.lower(policy.params, sub).compile()
            t_compiled = time.perf_counter()
            out, rep_s = repeated(lambda: compiled(policy.params, sub), FLAGS.reps, LONG_RUN_S)
            rep_ms = 1e3 * np.asarray(rep_s) / t_idx.shape[0]  # ms per batched action, per repetition
            actions, stats = jax.device_get(out)
            # where a method's wall time went (a GPU job's step limits are planned from these)
            seconds = {"build": t_built - t_build, "compile": t_compiled - t_built,
                       "total": time.perf_counter() - t_build}
            stats_all = {k: float(np.asarray(v).sum()) for k, v in stats.items()}
            bins = np.asarray(tok.to_bins(actions))
            same, dist = np.all(bins == ar_bins, -1), np.abs(bins - ar_bins).mean(-1)
            # How far the executed actions move the hand, against AR's on the same states (shorter
            # moves would finish tasks later: closed-loop time-outs).
            reach = float(np.linalg.norm(np.asarray(actions)[..., :3], axis=-1).mean())
            n_act = float(t_idx.size)
            ms = float(np.median(rep_ms))
            if base is None:  # AR, timed first
                base, base_reps, base_bins, base_reach = ms, rep_ms, bins, reach
            ratios = base_reps / rep_ms
            off_ar = np.abs(bins - base_bins).reshape(-1, bins.shape[-1])  # [actions, 7] bins from AR's
            label = cli.method_label(name, settings)
            row = {"method": name, "settings": settings, "label": label, "batch": b, "ms_per_action": ms,
                   "ms_reps": rep_ms.tolist(), "speedup_vs_ar": base / ms,
                   "speedup_spread": [float(ratios.min()), float(ratios.max())],
                   **{f"{k}_per_action": v / n_act for k, v in stats_all.items()},
                   "identical_to_ar": float(same.mean()), "mean_bin_distance_to_ar": float(dist.mean()),
                   "identical_to_ar_replay": float(np.all(off_ar == 0, -1).mean()),
                   "translation_vs_ar": reach / max(base_reach, 1e-12),
                   # per action dimension, on the same replayed states: mean |bin - AR's bin|, and the
                   # share of actions half the range or more from AR's (a saturated command reversed)
                   "bin_distance_to_ar_replay_per_dim": off_ar.mean(0).round(3).tolist(),
                   "reversed_vs_ar_replay_per_dim": (off_ar >= N_BINS // 2).mean(0).round(3).tolist(),
                   "replay_steps": int(t_idx.shape[0]), "seconds": {k: round(v, 1) for k, v in seconds.items()}}
            row["numerics"] = methods.numerics_ran(policy)
            if "target_passes" in stats_all:
                row["tokens_per_target_pass"] = stats_all.get("tokens", 7 * n_act) / max(stats_all["target_passes"], 1e-9)
            if policy.meta.get("cost_table") is not None:
                row["cost_table"] = dataclasses.asdict(policy.meta["cost_table"])
                row["runs_as_ar"] = bool(policy.meta.get("runs_as_ar", False))
            rows.append(row)
            if FLAGS.out:  # after every row: a run cut short (a step's time limit) keeps what it measured
                write(rows, query_ms)
            shares = ""
            if "skipped" in stats_all:
                shares = (f" retr-verified {row['retrieval_verified_per_action']:.2f} skipped "
                          f"{row['skipped_per_action']:.2f} drafter {row['drafter_mode_per_action']:.2f}")
            budget_shares = {k[len("budget_"):-len("_per_action")]: v for k, v in row.items()
                             if k.startswith("budget_") and k.endswith("_per_action") and v > 0}
            if budget_shares:
                shares += " budget " + " ".join(f"{k} {v:.2f}" for k, v in budget_shares.items())
            print(f"B={b:<4} {label:<60} {ms:8.2f} ms/action {row['speedup_vs_ar']:5.2f}x "
                  f"[{ratios.min():.2f}..{ratios.max():.2f}]  TPA {row.get('target_passes_per_action', 7):.2f}  "
                  f"AL {row.get('tokens_per_target_pass', 1):.2f}  =AR {row['identical_to_ar_replay']:.2f}  "
                  f"=rec {row['identical_to_ar']:.2f}  "
                  f"bins {row['mean_bin_distance_to_ar']:.2f}  move {row['translation_vs_ar']:.3f}{shares}  "
                  f"({seconds['build']:.0f} s to build, {seconds['compile']:.0f} to compile, "
                  f"{seconds['total']:.0f} in all)", flush=True)
    if FLAGS.plot:
        plot(rows, FLAGS.plot)


def write(rows, query_ms):
    results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "steps": FLAGS.steps,
                                             "record_method": FLAGS.record_method, "suites": FLAGS.suites,
                                             "device_loops": FLAGS.device_loops, "query_ms": query_ms, "rows": rows})


if __name__ == "__main__":
    cli.run(main)
