"""Where decoding time goes: a method's decode step broken into its parts, in closed loop.

  python -m experiments.profile --method=heisd --settings=top_k=4,depth=2,total_tokens=8 \
      --batch=256 --steps=50 --trace_dir=results/trace

Runs --steps control steps of --batch envs on the fixed evaluation initial states of
--suites with the method's policy. Every function is compiled once before timing (warm-up
excluded); at every step each part is timed on that step's observations with
`block_until_ready`:
  act           the method's whole decode step (what the rollout calls)
  ar            greedy AR decoding of the same observations (the baseline)
  prefill       the target's prompt pass (with the drafter's features)
  prefill+cand  the prefill with the retrieval candidates appended (fused verification)
  retrieval     the datastore query (kNN)
  draft_round   one EAGLE-2 tree (depth-1 drafter passes) + the drafter's update pass
  verify_round  one tree-verification target pass with acceptance and commit
  env_step      IK + physics + camera for the batch
and prints per-call medians, an estimated per-action breakdown of `act` (each part times
how often the method ran it per action, from its own statistics; the remainder is loop
and masking overhead) and act's speedup over AR at this batch size. --trace_dir also traces
3 calls each of `act`, `ar` and `env_step` at the last step's states under `jax.profiler`
(TensorBoard / Perfetto, one folder each) and prints and writes (`kernels`) their per-kernel
time per call on each device timeline (`heisd_jax.timing.kernel_summary`): where a part's
milliseconds go, kernel by kernel, and how much of a call the device spends waiting for the
host (the call's median wall time less its kernels), with the longest waits and the host
event each waited for (`timing.device_gaps`: a CUDA-graph launch, a `while`-loop condition
copied to the host, argument handling), and what the host ran of the call's control flow itself
(`timing.host_control`: conditionals and loops outside the CUDA graphs, their syncs, the graph
launches' host time). --hlo_dir writes the three calls' optimised HLO (gzipped
text), where those kernels' names (XLA's fusions) can be looked up.
act and every decode part (not the env step) are compiled with
`heisd_jax.xla_options.DEVICE_LOOPS`, as the public `heisd_jax.decode_action` is: on a GPU,
the draft rounds' loop and the budget's conditionals recorded into command buffers where each
of their branches can be (one holding a cuDNN convolution cannot: see `vla.Patchify`), which
process-wide XLA_FLAGS would also impose on the physics program. --nodevice_loops compiles
them with XLA's default command buffers (the comparison). --compiler_options adds per-program
XLA options to those programs alone (say, how command buffers are updated between calls).
--parts names the decode parts timed beside act and AR (default all; `--parts=` none, which at
a 7B target's size saves minutes of compiling when act's own time is the question).
"""

from __future__ import annotations

import functools
import time
from pathlib import Path

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
import numpy as np

from envs import tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import hybrid, results_io, retrieval, spec_decode as sd, target_model, timing, vla, xla_options
from heisd_jax.harness import methods, vla_policy
from experiments import cli

FLAGS = flags.FLAGS
cli.define_cost_flags()
flags.DEFINE_enum("method", "heisd", ["ar", "drafter", "retrieval", "heisd"], "Decoding method.")
flags.DEFINE_string("settings", "", "The method's settings, key=value,key=value (as in experiments.sweep).")
flags.DEFINE_string("suites", "goal", f"Suites of {list(tasks_lib.SUITES)} or 'all'.")
flags.DEFINE_integer("batch", 16, "Envs decoded together.")
flags.DEFINE_integer("steps", 30, "Timed control steps.")
flags.DEFINE_string("trace_dir", "", "Trace 3 calls of act and of env_step here and summarise them per kernel.")
flags.DEFINE_integer("top", 12, "Kernels listed per device timeline with --trace_dir.")
flags.DEFINE_string("hlo_dir", "", "Write the optimised HLO of act, ar and env_step here (the kernels' names).")
flags.DEFINE_bool("device_loops", True, "Compile act and every decode part with heisd_jax.xla_options.DEVICE_LOOPS, "
                  "as heisd_jax.decode_action is (GPU: loops and conditionals recorded into command buffers, run "
                  "without a host round trip per iteration); --nodevice_loops: XLA's default command buffers. The env "
                  "step is compiled as always.")
flags.DEFINE_string("compiler_options", "", "More per-program XLA options for act and every decode part (not the env "
                    "step), key=value,...: e.g. xla_gpu_command_buffer_update_mode=<a mode the installed XLA has>, to "
                    "time act with graphs that are not updated between calls. Checked by a one-element compile first.")
PARTS = ("prefill", "prefill+cand", "retrieval", "draft_round", "verify_round")
flags.DEFINE_list("parts", list(PARTS), f"Decode parts timed beside act, AR and the env step, of {list(PARTS)} (those "
                  "the method has); empty: none, which compiles two programs of the decode instead of up to eight (at "
                  "a 7B target's size, minutes).")
cli.define_paths("checkpoint", "drafter", "datastore")
flags.DEFINE_string("out", "", "Optional JSON output.")


def component_fns(meta: dict, name: str, jit=jax.jit):
    """Parts of the method's decode step (see the module docstring), each compiled by `jit`."""
    cfg, spec, hcfg = meta["cfg"], meta.get("spec"), meta.get("hcfg")
    tp = (lambda p: p["target"]) if name != "ar" else (lambda p: p)
    fns = {"ar": jit(lambda p, obs: target_model.ar_decode(tp(p), cfg, obs)[0]),
           "prefill": jit(lambda p, obs: vla.prefill_features(tp(p), cfg, obs))}
    if name == "ar":
        return fns

    def after_prefill(p, obs):
        logits, hidden, x, cache = vla.prefill_features(p["target"], cfg, obs)
        return sd.start(p["target"], p["drafter"], cfg, logits, hidden, x, cache, obs, slack=spec.depth + 1)

    def draft_round(p, s):
        tree = sd.draft_tree(p["drafter"], p["target"], cfg, spec, s.dcache, s.feat)
        return tree, sd.select_nodes(tree, spec.total_tokens)

    def verify_round(p, s, tree, sel):
        v = sd.verify(p["target"], cfg, spec, s.cache, s.root, tree, sel)
        return sd.advance(p["target"], p["drafter"], cfg, s, v)

    start = jit(after_prefill)
    fns.update(start=start, draft_round=jit(draft_round), verify_round=jit(verify_round))
    if hcfg is not None:
        def with_cand(p, obs, cand):
            return vla.prefill_with_block(p["target"], cfg, obs, *hybrid.candidate_block(cand))
        fns["prefill+cand"] = jit(with_cand)
        fns["retrieval"] = jit(lambda p, keys, task: retrieval.query(p["store"], keys, task, hcfg.n_candidates))
    return fns


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    try:
        settings = methods.check_settings(FLAGS.method, dict(kv.split("=", 1) for kv in FLAGS.settings.split(",") if kv))
        task_list = tasks_lib.get_tasks(FLAGS.suites)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if FLAGS.batch < 1 or FLAGS.steps < 1:
        raise app.UsageError("--batch and --steps must be >= 1")
    if unknown := sorted(set(FLAGS.parts) - set(PARTS)):
        raise app.UsageError(f"--parts: unknown {unknown}; valid parts: {list(PARTS)} (or none: --parts=)")
    want = set(FLAGS.parts)
    options = dict(xla_options.DEVICE_LOOPS) if FLAGS.device_loops else {}
    try:
        extra = xla_options.parse(FLAGS.compiler_options)
        options.update(extra)
        if extra:
            xla_options.check(options)
    except ValueError as e:
        raise app.UsageError(f"--compiler_options: {e}") from e
    env = TabletopEnv(task_list, methods.env_config(FLAGS.method, FLAGS.checkpoint))
    try:
        policy = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                     datastore=FLAGS.datastore, batch_size=FLAGS.batch,
                                     **cli.cost_kwargs(), **settings)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    meta = policy.meta
    hcfg = meta.get("hcfg")
    jit = functools.partial(jax.jit, compiler_options=options) if options else jax.jit
    fns = component_fns(meta, "ar" if meta.get("runs_as_ar") else FLAGS.method, jit)  # HeiSD where no option beats AR
    tids, keys = env.cycling_eval_starts(FLAGS.batch)
    states = jax.jit(jax.vmap(env.reset))(keys, jnp.asarray(tids, jnp.int32))
    params = policy.params
    pstate = policy.init(params, states)
    act = jit(policy.act)
    step = jax.jit(jax.vmap(env.step))
    act_keys = jnp.zeros((FLAGS.batch, 2), jnp.uint32)
    gidx = jnp.asarray(env.global_index, jnp.int32)

    def parts(states, pstate):
        obs = vla_policy.observation(states)
        out = {"ar": (fns["ar"], params, obs), "prefill": (fns["prefill"], params, obs)}
        if "start" in fns and want & {"draft_round", "verify_round"}:
            s = jax.block_until_ready(fns["start"](params, obs))
            tree, sel = jax.block_until_ready(fns["draft_round"](params, s))
            out.update(draft_round=(fns["draft_round"], params, s), verify_round=(fns["verify_round"], params, s, tree, sel))
        if hcfg is not None and want & {"retrieval", "prefill+cand"}:
            k = retrieval.make_keys(meta["key_spec"], meta["tok"], pstate.prev_actions, obs.proprio)
            task = gidx[states.info.task_id]
            cand = jax.block_until_ready(fns["retrieval"](params, k, task))[0]
            cand = jnp.concatenate([cand, pstate.recent], 1)  # the env's recent actions are verified too
            out.update(retrieval=(fns["retrieval"], params, k, task), **{"prefill+cand": (fns["prefill+cand"], params, obs, cand)})
        return {k: v for k, v in out.items() if k == "ar" or k in want}

    # Compile everything once (warm-up excluded from the timings).
    t0 = time.perf_counter()
    for fn, *args in parts(states, pstate).values():
        jax.block_until_ready(fn(*args))
    actions, _, _ = jax.block_until_ready(act(params, states, pstate, act_keys))
    jax.block_until_ready(step(states, actions))
    print(f"compiled in {time.perf_counter() - t0:.0f}s on {jax.devices()[0].device_kind}", flush=True)

    times: dict[str, list[float]] = {}
    totals: dict[str, float] = {}
    n_running = 0.0
    for t in range(FLAGS.steps):
        for k, (fn, *args) in parts(states, pstate).items():
            times.setdefault(k, []).append(timing.timed(lambda: fn(*args))[1])
        running = np.asarray(~states.done, np.float32)
        (actions, pstate, stats), dt = timing.timed(lambda: act(params, states, pstate, act_keys))
        times.setdefault("act", []).append(dt)
        for k, v in stats.items():
            totals[k] = totals.get(k, 0.0) + float((np.asarray(v) * running).sum())
        n_running += float(running.sum())
        states, dt = timing.timed(lambda: step(states, actions))
        times.setdefault("env_step", []).append(dt)
    kernels, gaps, control = {}, {}, {}
    obs = vla_policy.observation(states)
    calls = {"act": (act, (params, states, pstate, act_keys)), "ar": (fns["ar"], (params, obs)),
             "env_step": (step, (states, actions))}
    for name, (fn, args) in calls.items():  # after the timed loop, so tracing slows no timed call
        if FLAGS.trace_dir:
            path = timing.trace_calls(lambda: fn(*args), 3, Path(FLAGS.trace_dir) / name)
            kernels[name] = timing.kernel_summary(path, 3, FLAGS.top) if path else {}
            gaps[name] = timing.device_gaps(path, top=FLAGS.top) if path else {}
            control[name] = timing.host_control(path, 3) if path else {}
        if FLAGS.hlo_dir:
            timing.write_hlo(fn, args, Path(FLAGS.hlo_dir) / f"{name}.hlo.txt.gz")
    med = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
    per_action = {k: float(v) / max(n_running, 1.0) for k, v in totals.items()}
    print(f"\n{FLAGS.method} {settings or ''}  batch {FLAGS.batch}, {FLAGS.steps} steps, median ms per call:")
    for k in ("act", "ar", "prefill", "prefill+cand", "retrieval", "draft_round", "verify_round", "env_step"):
        if k in med:
            print(f"  {k:<14}{med[k]:9.3f}")
    breakdown = {}
    auto_budget = any(k.startswith("budget_") for k in per_action)
    if auto_budget:  # its rounds mix single-token passes and trees: rounds x (draft + verify) does not price them
        print("  (no per-action breakdown under budget=auto: its rounds are of several kinds)")
    elif FLAGS.method != "ar" and not {"prefill", "draft_round", "verify_round"} <= want:
        print("  (no per-action breakdown: --parts leaves out prefill, draft_round or verify_round)")
    elif FLAGS.method != "ar":
        rounds = per_action.get("rounds", 0.0)
        verified = per_action.get("retrieval_verified", 0.0)
        skipped = per_action.get("skipped", 0.0)
        breakdown["prefill"] = (1 - skipped) * (med["prefill"] + verified * (med.get("prefill+cand", med["prefill"])
                                                                            - med["prefill"]))
        breakdown["retrieval"] = med.get("retrieval", 0.0)
        breakdown["draft+verify rounds"] = rounds * (med["draft_round"] + med["verify_round"])
        breakdown["other (loop, masks, drafter prompt)"] = med["act"] - sum(breakdown.values())
        print(f"  per action ({rounds:.2f} rounds, {per_action.get('target_passes', 0):.2f} target passes, "
              f"{verified:.2f} retrieval-verified, {skipped:.2f} skipped):")
        for k, v in breakdown.items():
            print(f"    {k:<38}{v:9.3f} ms")
    speedup = med["ar"] / med["act"]
    print(f"  act vs AR at batch {FLAGS.batch}: {speedup:.2f}x (AR {med['ar']:.3f} ms, {FLAGS.method} {med['act']:.3f} ms); "
          f"env step {med['env_step']:.3f} ms")
    loop = {"act": 1e3 / (med["act"] + med["env_step"]), "ar": 1e3 / (med["ar"] + med["env_step"])}
    print(f"  host loop (decode + env step): {loop['act']:.1f} control steps/s with {FLAGS.method}'s act, "
          f"{loop['ar']:.1f} with AR's decode in its place")
    for name, lines in kernels.items():
        for line, summary in lines.items():
            idle = med[name] - summary["total_ms"]
            print(f"  {name} kernels, {line}: {summary['total_ms']:.3f} ms per call of {med[name]:.3f} "
                  f"(the device idle {idle:.3f} ms: launches, host syncs, argument handling)")
            for kname, ms in summary["top"]:
                print(f"    {ms:9.3f}  {kname[:150]}")
    for name, lines in gaps.items():
        for line, rows in lines.items():
            if rows:
                print(f"  {name}: the device idle >= 0.5 ms, {line} (3 calls; longest first):")
            for r in rows:
                host = f"{r['host'][:60]} ({r['host_ms']:.2f} ms)" if r["host"] else "no host event"
                print(f"    {r['ms']:7.3f} ms at {r['start_ms']:8.2f} ms, after {r['after'][:40]}: {host}")
    for name, c in control.items():
        if c:
            conds = ", ".join(f"{k} x{v:g}" for k, v in c["conditionals"].items()) or "none"
            print(f"  {name}, per call on the host: control flow run there: {conds}; {c['syncs']:g} device-to-host "
                  f"syncs; {c['graph_launches']:g} CUDA-graph launches, {c['graph_launch_ms']:.3f} ms "
                  f"(updates {c['graph_update_ms']:.3f} ms)")
    if FLAGS.trace_dir:
        print(f"  trace: {FLAGS.trace_dir} (tensorboard --logdir {FLAGS.trace_dir})")
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "method": FLAGS.method,
                                                 "settings": settings, "numerics": methods.numerics_ran(policy),
                                                 "batch": FLAGS.batch, "steps": FLAGS.steps,
                                                 "device_loops": FLAGS.device_loops,
                                                 "parts": sorted(want),
                                                 "compiler_options": options, "median_ms": med,
                                                 "per_action": per_action, "breakdown_ms": breakdown,
                                                 "speedup_vs_ar": speedup,
                                                 "control_steps_per_s": loop, "kernels": kernels,
                                                 "device_gaps": gaps, "host_control": control})


if __name__ == "__main__":
    cli.run(main)
