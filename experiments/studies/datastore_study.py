"""Which datastore would the target accept: retrieval drafts from the shipped datastore
against datastores built from the target's own closed-loop rollouts, with other values and
other keys (issue "HeiSD on a target that succeeds", lever "datastore keys and contents").

  python -m experiments.studies.datastore_study --suites=spatial --store_envs=80 --query_envs=40 --steps=150 \
      --out=results/datastore_study.json

Records the target (greedy AR) on `--store_envs` training initial states (the datastore's
episodes) and on `--query_envs` fixed evaluation states (the held-out queries), the scripted
expert watching every step without acting. Each datastore below is then measured on the
same held-out running steps with HeiSD's own verification (`heisd_jax.harness.offline.boundary.
measure`, as the boundary calibration does: the retrieved candidates verified first, drafter
rounds for what they leave):

  shipped           the shipped datastore (expert demonstrations; key: the last executed
                    actions, TCP pose and gripper, `retrieval.make_keys`)
  rollouts/target   the store episodes' steps, keyed alike; value: the action the target
                    executed there (its greedy action)
  rollouts/expert   the same states and keys; value: the expert's action (DAgger's label)
  + prev feature    rollouts/target keyed by the key above and the target's last-layer
                    feature of the *previous* step's prompt (available before this step's
                    prefill, so candidates can still ride in it)
  + this feature    the same with this step's feature (an upper bound: it needs the prefill
                    before the query, one more target pass per step)

  ... + recent actions  the same with the env's last `recent_candidates` executed actions
                    verified beside the retrieved ones, as `--method=heisd` does; and the
                    recent actions alone

Prints per datastore: entries, target passes per action with retrieval first (TPA), the
best candidate's mean accepted length and the share of steps where one was accepted whole;
the drafter alone's TPA (once) as the reference.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
from envs import expert, rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import results_io, retrieval, vla
from heisd_jax.harness import methods, vla_policy
from heisd_jax.harness.offline import boundary, datastore
from experiments import cli

FLAGS = flags.FLAGS
cli.define_paths("checkpoint", "drafter", "datastore")
flags.DEFINE_string("suites", "spatial", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names.")
flags.DEFINE_integer("store_envs", 80, "Target rollouts on training initial states that the built datastores hold.")
flags.DEFINE_integer("query_envs", 40, "Target rollouts on the fixed evaluation states whose steps are the queries.")
flags.DEFINE_integer("steps", 150, "Control steps recorded per env (an episode that ends early stops counting).")
flags.DEFINE_string("settings", "", "heisd settings as key=value,key=value (as in experiments.sweep).")
flags.DEFINE_integer("batch", 256, "Steps decoded at once.")
flags.DEFINE_string("out", "results/datastore_study.json", "Results JSON.")


def _record(env, learner, tids, keys, steps, history):
    """The running steps of target rollouts (boundary.closed_loop_steps' columns), plus the
    action the target executed ("action") and the expert's label ("label") at each."""
    run = jax.jit(lambda p, k, t: rollout.record_episodes(env, dataclasses.replace(learner, params=p), k, t, steps,
                                                          teacher=expert.observer(env), beta=0.0))
    final, traj = jax.device_get(run(learner.params, keys, jnp.asarray(tids, jnp.int32)))
    n = np.asarray(final.step)
    cols, _ = boundary.closed_loop_steps(traj, n, np.asarray(env.instructions)[tids],
                                         np.asarray(env.global_index)[tids], history)
    cols["action"] = np.concatenate([traj["policy_action"][: n[b], b] for b in range(len(n)) if n[b]])
    cols["label"] = np.concatenate([traj["action"][: n[b], b] for b in range(len(n)) if n[b]])
    cols["start"] = np.concatenate([np.arange(n[b]) == 0 for b in range(len(n)) if n[b]])
    return cols


def _recent(tok, cols, r):
    """The env's last r executed actions before each step as token ids [N, r, 7], newest
    first, and which exist [N, r] (fewer at an episode's start)."""
    starts = np.flatnonzero(cols["start"])
    ids, valid = [], []
    for a, b in zip(starts, list(starts[1:]) + [len(cols["start"])]):
        hist = datastore.episode_history(np.asarray(cols["action"][a:b], np.float32), r)[:, ::-1]
        ids.append(np.asarray(tok.to_ids(jnp.asarray(hist))))
        valid.append(np.arange(b - a)[:, None] > np.arange(r)[None, :])
    return np.concatenate(ids).astype(np.int32), np.concatenate(valid)


def _features(params, cfg, cols, batch):
    """The target's last-layer feature at the last prompt position of every step [N, D], and
    the previous step's (zeros at an episode's start)."""
    fn = jax.jit(lambda p, im, ins, pr: vla.prefill(p, cfg, vla.Observation(image=im, instruction=ins, proprio=pr))[1])
    feat = datastore.in_batches(lambda idx: fn(params, *(cols[k][idx] for k in ("image", "instruction", "proprio"))),
                                len(cols["task"]), batch).astype(np.float32)
    prev = np.concatenate([np.zeros_like(feat[:1]), feat[:-1]])
    prev[cols["start"]] = 0.0
    return feat, prev


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    for name in ("store_envs", "query_envs", "steps", "batch"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1, got {getattr(FLAGS, name)}")
    try:
        task_list = tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
        settings = methods.check_settings("heisd", dict(kv.split("=", 1) for kv in FLAGS.settings.split(",") if kv))
        env = TabletopEnv(task_list, methods.env_config("heisd", FLAGS.checkpoint))
        paths = cli.paths("checkpoint", "drafter", "datastore")
        stack, cfg, tok, hcfg, key_spec, _ = methods.load_hybrid("heisd", paths, settings, env)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    params, shipped = stack["target"], stack["store"]
    learner = vla_policy.decoding_policy("ar", params, cfg, tok, vla_policy.ar)

    t0 = time.perf_counter()
    n_tasks = len(task_list)
    store_tids = (np.arange(FLAGS.store_envs) % n_tasks).astype(np.int32)
    store_keys = env.initial_state_keys(store_tids, np.arange(FLAGS.store_envs) // n_tasks, split="train")
    held = _record(env, learner, store_tids, store_keys, FLAGS.steps, key_spec.history)
    query_tids, query_keys = env.cycling_eval_starts(FLAGS.query_envs)
    query = _record(env, learner, query_tids, query_keys, FLAGS.steps, key_spec.history)
    print(f"recorded {len(held['task'])} store steps and {len(query['task'])} held-out steps in "
          f"{time.perf_counter() - t0:.0f}s", flush=True)

    feat, prev_feat = _features(params, cfg, held, FLAGS.batch)
    qfeat, qprev_feat = _features(params, cfg, query, FLAGS.batch)
    base = np.asarray(retrieval.make_keys(key_spec, tok, held["prev"], held["proprio"]))
    qbase = np.asarray(retrieval.make_keys(key_spec, tok, query["prev"], query["proprio"]))
    mu, sd = feat.mean(0), feat.std(0) + 1e-6
    scale = np.sqrt(base.shape[1] / feat.shape[1])  # the feature part weighs about as much as the base key

    def with_feat(k, f):
        return np.concatenate([k, (f - mu) / sd * scale], 1)

    values = {"target": np.asarray(tok.to_ids(jnp.asarray(held["action"]))),
              "expert": np.asarray(tok.to_ids(jnp.asarray(held["label"])))}

    def variant(store, keys=None, recent=False, retrieved=True):
        """A datastore to measure: its store, the held-out keys (None: make_keys), whether the
        env's recent actions are verified too and whether retrieved candidates are."""
        return dict(store=store, keys=keys, recent=recent, retrieved=retrieved)

    def rollouts(values_of, keys=base, query_keys=None):
        return variant(retrieval.Datastore.of(keys, values[values_of], held["task"]), query_keys)

    variants = {
        "shipped": variant(shipped),
        "rollouts/target": rollouts("target"),
        "rollouts/expert": rollouts("expert"),
        "rollouts/target + prev feature": rollouts("target", with_feat(base, prev_feat), with_feat(qbase, qprev_feat)),
        "rollouts/target + this feature": rollouts("target", with_feat(base, feat), with_feat(qbase, qfeat)),
    }
    for name in ("shipped", "rollouts/target", "rollouts/target + prev feature"):  # as heisd verifies them
        variants[f"{name} + recent actions"] = dict(variants[name], recent=True)
    n = hcfg.n_candidates
    nowhere = retrieval.Datastore.of(base[:n], values["target"][:n], [-1] * n)  # no query's task: nothing retrieved
    variants["recent actions alone"] = variant(nowhere, recent=True, retrieved=False)
    recent, recent_valid = _recent(tok, query, hcfg.recent_candidates)
    rows = []
    print(f"\n{'datastore':<46}{'entries':>8}{'TPA retr':>10}{'accepted':>10}{'whole':>8}{'TPA draft':>11}")
    for name, v in variants.items():
        steps = {**{k: query[k] for k in ("image", "instruction", "proprio", "prev", "task", "feat")},
                 **({} if v["keys"] is None else {"key": v["keys"]}),
                 **({"recent": recent, "recent_valid": recent_valid} if v["recent"] else {})}
        m = boundary.measure(dict(stack, store=v["store"]), cfg, hcfg, key_spec, tok,
                             steps, FLAGS.batch, drafter_alone=not rows)  # the drafter's TPA: the same for every store
        row = {"datastore": name, "entries": int(v["store"].size) if v["retrieved"] else 0, "recent": v["recent"],
               **boundary.group_table(m, np.zeros(len(m["metric"]), np.int32), ("all",))[0]}
        if rows:  # measured once, on the first store
            del row["tpa_drafter"]
        rows.append(row)
        print(f"{name:<46}{row['entries']:>8}{row['tpa_retrieval']:>10.2f}{row['retrieval_accepted']:>10.2f}"
              f"{row['retrieval_whole']:>8.1%}{rows[0]['tpa_drafter']:>11.2f}", flush=True)
    record = {**results_io.provenance(cli.command_line()), "store_steps": len(held["task"]),
              "held_out_steps": len(query["task"]), "settings": settings, "rows": rows}
    Path(FLAGS.out).parent.mkdir(parents=True, exist_ok=True)
    results_io.write_json_atomic(FLAGS.out, record)
    print(f"results: {os.path.abspath(FLAGS.out)}")


if __name__ == "__main__":
    cli.run(main)
