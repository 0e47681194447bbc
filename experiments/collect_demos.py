"""Collects demonstrations into an envs.demos dataset: the scripted expert's own episodes, or
(DAgger) the expert's labels on the states a VLA policy visits.

  python -m experiments.collect_demos --suites=all --episodes_per_task=50 --num_envs=256 \
      --wrist --out=data/demos
  python -m experiments.collect_demos --policy=runs/vla0 --beta=0.3 --first_episode=1000 \
      --out=data/dagger1           # DAgger: the policy drives, the expert labels

The env batch is split over every local device (--devices): each steps its share of the envs,
and the trajectories are gathered on the host. Episodes use the training initial-state keys
(disjoint from the 50 evaluation states).
Expert episodes are kept only when successful; DAgger episodes are kept whole (the states
where the policy goes wrong are the point). The dataset appears at --out only once complete.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags, logging
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

import envs  # noqa: F401  (XLA CPU flag before JAX starts)
from envs import camera, demos, expert, rollout, scene, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from experiments import cli
from heisd_jax import sharding, xla_options
from heisd_jax.harness import executable_store as store_lib
from heisd_jax.timing import Phases

FLAGS = flags.FLAGS
flags.DEFINE_string("suites", "all", f"Comma-separated suites of {list(tasks_lib.SUITES)}, or 'all'.")
flags.DEFINE_list("tasks", [], "Only these task names.")
flags.DEFINE_integer("episodes_per_task", 50, "Training episodes attempted per task.")
flags.DEFINE_list("suite_weights", [], "SUITE:N or TASK:N,...: the tasks of these suites, or these tasks, get N times "
                  "--episodes_per_task (e.g. spatial:2,long:2 for the suites a policy fails most); a task's own "
                  "weight overrides its suite's; others 1.")
flags.DEFINE_string("weights_from", "", "A DAgger dataset (this command with --policy) or an evaluation's results "
                    "JSON: each task gets episodes in proportion to how often that policy failed it "
                    "(envs.tasks.failure_weights, up to 4x); a task named in --suite_weights keeps the weight given there.")
flags.DEFINE_bool("keep_total", False, "With --weights_from: collect as many episodes per time limit as "
                  "--episodes_per_task and --suite_weights alone give, shared out among that limit's tasks in "
                  "proportion to the weights with the failures' added (envs.tasks.shared_episode_counts): a policy "
                  "that fails everywhere does not multiply the collection, and the batches keep their shapes, so "
                  "every round runs one compiled program.")
flags.DEFINE_integer("num_envs", 64, "Episodes run in parallel, split over --devices (a multiple of their number).")
flags.DEFINE_integer("devices", 0, "Local devices the env batch is split over, data parallel (0: all of them).")
flags.DEFINE_integer("image_size", 64, "Camera resolution of each view (square).")
flags.DEFINE_bool("wrist", True, "Also render the wrist camera (tiled right of the agent view).")
flags.DEFINE_string("policy", "", "DAgger: a VLA checkpoint that drives the episodes (greedy AR) while the expert "
                    "labels every visited state; its camera settings are used. Empty: the expert drives.")
cli.existing_dir("policy", "policy checkpoint")
flags.DEFINE_float("beta", 0.0, "DAgger: probability of executing the expert's action instead of the policy's, "
                   "per env and step.")
flags.DEFINE_float("action_noise", 0.1, "Std of Gaussian noise added to the executed motion actions (diversity); "
                   "the recorded labels are the expert's clean actions.")
flags.DEFINE_float("expert_rot_gain", expert.ExpertConfig.rot_gain, "The expert's rotation action per (error / max "
                   "step): at the default it saturates beyond ~0.1 rad of error; lower keeps its labels proportional "
                   "over more of a turn (envs.expert.ExpertConfig.rot_gain, docs/target.md).")
flags.DEFINE_integer("first_episode", 0, "Index of the first training initial state (to extend a dataset).")
flags.DEFINE_string("out", "data/demos", "Output dataset directory.")
flags.DEFINE_bool("overwrite", False, "Replace an existing dataset at --out (only once the new one is complete).")
flags.DEFINE_bool("deterministic", True, "Compile the collection with deterministic GPU reductions "
                  "(heisd_jax.xla_options.DETERMINISTIC), so a rerun writes the same dataset. Without it the "
                  "simulator's scatter-adds use atomics on a GPU, and a rare episode ends a step apart from one run "
                  "to the next (docs/target.md); with it the device run takes ~1.35x as long.")
cli.define_store_flag()


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    task_list = cli.task_list(FLAGS.suites, FLAGS.tasks)
    for name in ("episodes_per_task", "num_envs", "image_size"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1")
    if not 0.0 <= FLAGS.beta <= 1.0:
        raise app.UsageError(f"--beta must be in [0, 1], got {FLAGS.beta}")
    if FLAGS.beta and not FLAGS.policy:
        raise app.UsageError("--beta needs --policy (without one the expert drives every step)")
    if FLAGS.first_episode < 0:
        raise app.UsageError("--first_episode must be >= 0")
    if FLAGS.expert_rot_gain <= 0:
        raise app.UsageError(f"--expert_rot_gain must be > 0, got {FLAGS.expert_rot_gain}")
    if FLAGS.keep_total and not FLAGS.weights_from:
        raise app.UsageError("--keep_total needs --weights_from (without failure weights there is nothing to share out)")
    mesh = device_mesh(FLAGS.devices, FLAGS.num_envs)
    try:
        failures = cli.failure_weights(FLAGS.weights_from) if FLAGS.weights_from else []
        weights = tasks_lib.parse_suite_weights(failures + list(FLAGS.suite_weights))
        if FLAGS.keep_total:
            given = tasks_lib.parse_suite_weights(FLAGS.suite_weights)
            counts = tasks_lib.shared_episode_counts(task_list, FLAGS.episodes_per_task, given, weights)
        else:
            counts = tasks_lib.episode_counts(task_list, FLAGS.episodes_per_task, weights)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    dagger = bool(FLAGS.policy)
    if dagger:
        from heisd_jax.harness import methods  # noqa: PLC0415

        try:
            env_cfg = methods.env_config("ar", FLAGS.policy)
            env = TabletopEnv(task_list, env_cfg)
            learner = methods.make_policy("ar", env, checkpoint=FLAGS.policy)
        except ValueError as e:
            raise app.UsageError(str(e)) from e
    else:
        env = TabletopEnv(task_list, EnvConfig(camera=camera.CameraConfig(
            height=FLAGS.image_size, width=FLAGS.image_size, wrist=FLAGS.wrist)))
    cam = env.config.camera
    expert_cfg = expert.ExpertConfig(rot_gain=FLAGS.expert_rot_gain)
    policy = expert.policy(env, expert_cfg)
    meta = dict(
        suites=sorted({t.suite for t in task_list}),
        tasks=[{"name": t.name, "suite": t.suite, "instruction": t.instruction} for t in task_list],
        image_size=cam.height, views=list(cam.views), control_dt=scene.CONTROL_DT,
        executed_action_noise=FLAGS.action_noise,
        labels="expert actions on the policy's states (DAgger)" if dagger else "clean expert actions",
        policy=FLAGS.policy or "expert", beta=FLAGS.beta if dagger else 1.0,
        expert=dataclasses.asdict(expert_cfg),
        episode_weights={t.name: tasks_lib.episode_weight(t, weights) for t in task_list},
        episodes_per_task=counts,
        split="train",
    )
    writer = demos.DatasetWriter(FLAGS.out, meta, overwrite=FLAGS.overwrite)
    pairs = [(t, FLAGS.first_episode + e) for t, task in enumerate(task_list) for e in range(counts[task.name])]
    batches = horizon_batches(pairs, [t.max_steps for t in task_list], FLAGS.num_envs, multiple=mesh.size)
    # One program for the whole collection: the policy's parameters, beta and each batch's time
    # limit are arguments, not constants baked in, so batches of every limit, and every DAgger
    # round of a build (through the persistent compilation cache), run the same executable.
    params = sharding.replicate(mesh, learner.params) if dagger else None
    n_steps = max(limit for limit, _, _ in batches)

    def record_fn(p, beta, keys, tids, limit):
        acting = dataclasses.replace(learner, params=p) if dagger else policy
        mix = dict(teacher=policy, beta=beta) if dagger else {}
        return rollout.record_episodes(env, acting, keys, tids, n_steps, exec_noise=FLAGS.action_noise, limit=limit, **mix)

    programs, stored = {}, []
    options = xla_options.determinism(FLAGS.deterministic)
    beta = jnp.float32(FLAGS.beta)
    # What the program closes over beyond its inputs' shapes (the code is in the store's key):
    # the policy's parameters are an input, so every DAgger round of a build, driven by another
    # policy of one architecture, loads the first round's program without tracing it.
    store = store_lib.ExecutableStore(FLAGS.executable_store) if FLAGS.executable_store else None
    identity = {"program": "experiments.collect_demos", "env": env.config, "tasks": env.tasks,
                "devices": [d.id for d in mesh.devices.flat], "compiler_options": options,
                "policy": learner.name if dagger else "expert", "meta": learner.meta if dagger else None,
                "expert": expert_cfg,
                "n_steps": n_steps, "exec_noise": FLAGS.action_noise}

    def launch(batch, limit):
        """Compiles (or loads) the batch size's program once and starts the batch on the
        devices; returns without waiting, so the host can fetch the previous batch meanwhile."""
        size = batch[0].shape[0]
        if size not in programs:
            phases.lap("run")
            with jax.set_mesh(mesh):  # the camera kernel splits its batch as the envs are split
                programs[size], hit = store_lib.compile_or_load(
                    store, identity, jax.jit(record_fn), (params, beta, *batch, jnp.int32(limit)), options)
            stored.append(hit)
            phases.lap("compile")
        return programs[size](params, beta, *batch, jnp.int32(limit))

    def start_fetch(running, n):
        """Waits for the batch, then queues the slicing of its first `n` envs (the batch's
        own, not its padding) up to the last step any of them ran, and starts copying that to
        the host: the rest of the buffers (padded env slots, steps after every episode ended)
        stays on the devices. Returns the function that finishes the copy: (success, step
        count, trajectories) on the host. Queued before the next batch, the slicing does not
        wait for it, and the copy travels while it runs."""
        final, traj = running
        success, step = sharding.fetch_slice((final.success, final.step), (slice(0, n),))  # waits for the batch
        finish = sharding.start_fetch_slice(traj, (slice(0, int(step.max(initial=0))), slice(0, n)))

        def done():
            phases.lap("run")
            out = success, step, finish()
            phases.lap("fetch")
            return out
        return done

    agree = [0, 0]  # DAgger: steps where the policy's action token equals the expert's, steps
    kept = 0

    def write(chunk, success, step, traj):
        """Slices the batch's episodes (a DAgger round keeps every one, the expert's only its
        successes) and adds them to the dataset as one shard; returns how many it kept."""
        phases.lap("run")
        steps, records, row = {f: [] for f in demos.STEP_FIELDS}, [], 0
        for i, (t, e) in enumerate(chunk):
            if not (success[i] or dagger):
                continue
            n = int(step[i])
            if dagger:
                same = np.abs(traj["policy_action"][:n, i] - traj["action"][:n, i]) <= 1.0 / 128
                agree[0] += int(same.all(-1).sum())
                agree[1] += n
            for f in demos.STEP_FIELDS:
                steps[f].append(traj[f][:n, i])
            task = task_list[t]
            records.append(dict(task=task.name, suite=task.suite, task_index=t, instruction=task.instruction,
                                episode=int(e), start=row, length=n, success=bool(success[i])))
            row += n
        if records:
            writer.add_shard({f: np.concatenate(v) for f, v in steps.items()}, records)
        phases.lap("host")
        return len(records)

    # The loop's seconds, lapped by launch, start_fetch and write: whatever of it is not
    # compiling, fetching or writing is the devices running (or the host waiting on them),
    # lapped as "run": where the host blocks moves with the overlap, so it is not timed at one call.
    phases = Phases(seconds=dict(compile=0.0, run=0.0, fetch=0.0, host=0.0))
    try:
        with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} episodes"),
                      TextColumn("kept {task.fields[kept]}"), TimeRemainingColumn()) as bar:
            job = bar.add_task("collecting", total=len(pairs), kept=0)
            # Batch k+1 runs on the devices while batch k's trajectories travel to the host
            # and are written: its slicing is queued first, then batch k+1, then the host
            # waits for the copy.
            fetching = None
            for item in [*batches, None]:
                running = None
                if item is not None:
                    limit, size, chunk = item
                    pad = chunk + [chunk[-1]] * (size - len(chunk))
                    tids, eps = np.array(pad).T
                    keys = env.initial_state_keys(tids, eps, split="train")
                    running = launch(sharding.shard_batch(mesh, (keys, jnp.asarray(tids, jnp.int32))), limit)
                if fetching is not None:
                    finish, done_chunk = fetching
                    kept += write(done_chunk, *finish())
                    bar.update(job, advance=len(done_chunk), kept=kept)
                fetching = (start_fetch(running, len(chunk)), chunk) if running is not None else None
        phases.lap("run")
        path = writer.finalize()
        phases.lap("host")
    except BaseException:
        writer.abort()
        raise
    phases.lap("run")
    phases.notes.update(compile=f"{len(programs)} programs, {sum(stored)} loaded from the executable store",
                        run=f"{len(batches)} batches over {mesh.size} devices", host="episodes sliced and written")
    print(phases.line())
    if dagger:
        n_succ = sum(r.get("success", False) for r in demos.DemoDataset(path).episodes)
        print(f"DAgger: {kept} episodes, policy success {n_succ / max(kept, 1):.1%} (beta {FLAGS.beta}); policy action "
              f"within 1/128 of the expert's in all 7 dims on {agree[0] / max(agree[1], 1):.1%} of {agree[1]} steps "
              f"-> {path}")
    else:
        print(f"kept {kept}/{len(pairs)} successful episodes ({kept / len(pairs):.1%}) -> {path}")


def device_mesh(devices: int, num_envs: int):
    """The env mesh over the first `devices` local devices (0: all); UsageError when there are
    fewer, or when they cannot split `num_envs` evenly."""
    try:
        mesh = sharding.local_mesh(devices)
    except ValueError as e:
        raise app.UsageError(f"--{e}") from None
    try:
        sharding.check_batch(num_envs, mesh)
    except ValueError as e:
        raise app.UsageError(f"--num_envs: {e}") from None
    return mesh


def horizon_batches(pairs: list[tuple[int, int]], max_steps: list[int], num_envs: int, multiple: int = 1
                    ) -> list[tuple[int, int, list[tuple[int, int]]]]:
    """Splits (task index, episode) pairs into batches of at most `num_envs` that each hold
    tasks of one time limit: [(limit, batch size, pairs)]. A batch runs to its longest task's
    limit, so a 220-step task batched with 420-step ones would be simulated (and its frames
    recorded) for nearly twice its own limit. Every batch has one size, so that one compiled
    program (whose time limit is an argument) runs them all: the largest that any limit's
    batches need, each limit's as small as its batch count allows (fewer padded slots than
    batches, not up to `num_envs`), rounded up to a `multiple` (the devices the batch is split
    over; `num_envs` must be one). A padded slot costs a repeated episode's simulation, which
    is far cheaper than compiling a second program."""
    by_limit: dict[int, list[tuple[int, int]]] = {}
    for t, e in pairs:
        by_limit.setdefault(int(max_steps[t]), []).append((t, e))
    sizes = {}
    for limit, group in by_limit.items():
        n_batches = -(-len(group) // num_envs)
        per_batch = -(-len(group) // n_batches)  # ceiling divisions
        sizes[limit] = -(-per_batch // multiple) * multiple
    size = max(sizes.values())
    return [(limit, size, group[i: i + sizes[limit]]) for limit, group in sorted(by_limit.items())
            for i in range(0, len(group), sizes[limit])]


if __name__ == "__main__":
    cli.run(main)
