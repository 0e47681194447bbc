"""The batched evaluator: runs a policy on the fixed evaluation initial states of a set of
tasks, `num_envs` episodes at a time under one jitted rollout (the env batch sharded over
all devices, see `sharding`), and aggregates success rates per task and suite. Progress is
handed to callbacks after every batch, and within a refilled queue every `save_every_s`
seconds, so callers can persist results as episodes end and resume an interrupted run. A
caller's `stop` (say, set by a signal) ends a queue after the round in progress, its ended
episodes handed over first (`EvaluationStopped`).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import time
from typing import Any, Callable, Collection, Sequence

import jax
import numpy as np

from envs import rollout, tasks as tasks_lib
from envs.env import TabletopEnv
from heisd_jax import sharding, xla_options
from heisd_jax.harness import executable_store


class EvaluationStopped(Exception):
    """`evaluate` ended early because its `stop()` said so, after handing the episodes that
    had ended to `on_progress` (`results`: everything so far). `timing`: the stopped call's
    share, as `on_batch`'s timing for a call (its episodes: those that ended; its env steps:
    theirs and the running episodes' so far); None when it stopped before a call."""

    def __init__(self, results: dict[str, list], timing: dict | None = None):
        super().__init__("evaluation stopped on request")
        self.results, self.timing = results, timing


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    episodes_per_task: int = tasks_lib.N_EVAL_INIT_STATES
    num_envs: int = 64  # episodes run in parallel
    # An env whose episode ends takes the next pending one (all pending episodes in one call),
    # instead of batches of num_envs episodes that each wait for their slowest episode.
    refill: bool = True
    # With refill: once the queue is empty and at most this many envs still run, they go on
    # in a batch of this size (`rollout.run_queue`); 0: the tail runs at num_envs.
    tail_envs: int = 0
    # Compile the rollout with deterministic GPU reductions (`xla_options.DETERMINISTIC`: the
    # physics' scatter-adds without atomics), so a rerun plays the same episodes; slower.
    deterministic: bool = False
    # With refill: every this many seconds of a call, the episodes that have ended so far are
    # handed to `evaluate`'s on_progress (to be saved), so an interrupted queue resumes after
    # them instead of from its start; 0: only at the end of each call.
    save_every_s: float = 60.0

    def __post_init__(self):
        if not 1 <= self.episodes_per_task <= tasks_lib.N_EVAL_INIT_STATES:
            raise ValueError(f"episodes_per_task must be in 1..{tasks_lib.N_EVAL_INIT_STATES}, got {self.episodes_per_task}")
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {self.num_envs}")
        if not 0 <= self.tail_envs < self.num_envs:
            raise ValueError(f"tail_envs must be 0 (off) or in 1..{self.num_envs - 1} (below num_envs), "
                             f"got {self.tail_envs}")
        if self.tail_envs and not self.refill:
            raise ValueError("tail_envs needs refill (a static batch has no queue to drain)")
        if self.save_every_s < 0:
            raise ValueError(f"save_every_s must be >= 0 (0: save at the end of each call only), got {self.save_every_s}")


NUM_ENVS_PER_GPU = 512  # env slots per GPU when none are asked for (`default_num_envs`)


def default_num_envs(devices: Sequence[jax.Device] | None = None) -> int:
    """Env slots when none are asked for: `NUM_ENVS_PER_GPU` per GPU of `devices` (default: all),
    else `EvalConfig.num_envs`. On one H100, AR's 2,000-episode evaluation ran 46 s at 512 slots
    against 64 s at 1,000: a control step's cost grows with the slots, and past ~500 the run is
    bound by the long suite's 420-step limit (BENCHMARKS.md)."""
    devices = jax.devices() if devices is None else devices
    if devices[0].platform == "gpu":
        return NUM_ENVS_PER_GPU * len(devices)
    return EvalConfig.num_envs


def pending_episodes(env: TabletopEnv, cfg: EvalConfig, done: dict[str, list],
                     tasks: Collection[str] | None = None) -> list[tuple[int, int]]:
    """(task index, episode) pairs not yet in `done` (task name -> per-episode results), of
    the env's tasks named in `tasks` (default: all)."""
    out = []
    for t, task in enumerate(env.tasks):
        if tasks is not None and task.name not in tasks:
            continue
        have = done.get(task.name, [None] * cfg.episodes_per_task)
        out += [(t, e) for e in range(cfg.episodes_per_task) if e >= len(have) or have[e] is None]
    return out


# XLA compiles a program on one thread (its backend's kernels aside): a rollout's programs
# compile side by side here, and a tail's beside the head's run.
_COMPILER = concurrent.futures.ThreadPoolExecutor(8, thread_name_prefix="heisd-compile")


def _shapes(tree) -> list[jax.ShapeDtypeStruct]:
    """The shapes and dtypes of `tree`'s leaves, as a store key's inputs: the same whether the
    tree came from a traced program or a loaded one (their shardings print differently), and
    without MJX's tree, whose text holds object ids."""
    return [jax.ShapeDtypeStruct(np.shape(x), x.dtype) for x in jax.tree.leaves(tree)]


class BatchRollout:
    """The jitted rollout of `queue` episodes in `num_envs` env slots, sharded over `devices`
    (default: all; the env slots are split, the policy's parameters replicated; one device: a
    plain jit). queue == num_envs: one static batch, one program run until every env is done.
    queue > num_envs: a slot whose episode ends takes the next pending one, as
    `rollout.run_queue` runs it, but as programs the host drives (`rollout.queue_loop`): the
    episodes' starts (`rollout.queue_starts`); `first` (the slots filled, the first action and
    IK); the physics substeps; and `turn` (the derived state, camera and outcomes of one step,
    then the next refill, action and IK). XLA compiles a program on one thread, so they compile
    side by side: the physics as soon as it is lowered, the others once all are traced.
    Compiled ahead of time, so that calls time execution only.
    `seed=None`: the seed is an input (`inputs(..., seed=)`), so one program serves every seed.
    `store`: compiled programs are loaded from it, and stored in it when compiled, where the
    backend supports it (`executable_store.supported`); the key adds this rollout's env, policy
    and sizes to the store's identity. `tail_envs` (with a queue): the loop stops where the
    tail starts, and the tail goes on as a queue loop of `tail_envs` slots from the head's
    carry (`rollout.queue_loop`: `run_queue_tail` as programs), traced and compiled in the
    background while the head runs, so that its compile adds to the wall time only where it
    outlasts the head."""

    _tail = _starts = _loop = None

    def __init__(self, env: TabletopEnv, policy: rollout.Policy, num_envs: int, seed: int | None = 0,
                 devices: Sequence[jax.Device] | None = None, queue: int | None = None, tail_envs: int = 0,
                 store: executable_store.ExecutableStore | None = None, deterministic: bool = False):
        self.env, self.num_envs, self._tail_envs = env, num_envs, tail_envs
        self._options = xla_options.determinism(deterministic)
        self.queue = num_envs if queue is None else queue
        if self.queue < num_envs:
            raise ValueError(f"queue ({self.queue}) must hold at least num_envs ({num_envs}) episodes")
        self.mesh = sharding.env_mesh(devices)
        sharding.check_batch(num_envs, self.mesh)
        if tail_envs:
            sharding.check_batch(tail_envs, self.mesh)
        self.devices = self.mesh.size
        self.params = sharding.replicate(self.mesh, policy.params)
        max_steps = int(max(t.max_steps for t in env.tasks))
        self.seed_input = seed is None
        if self.queue == num_envs:
            def run(params, k, t, n_valid, seed_in=seed):
                del n_valid  # padding rows of a static batch are run and ignored
                final, totals, steps = rollout.run_episodes(env, dataclasses.replace(policy, params=params), k, t,
                                                            max_steps, seed_in)
                return rollout.EpisodeResults.of(final, totals), steps
            self._run = jax.jit(run)
        else:
            bound = max_steps * -(-self.queue // num_envs) + self.queue  # refills wait at most a step each
            constrain = sharding.slot_constraint(self.mesh)

            def starts(k, t, seed_in=seed):  # every queued episode's reset
                return rollout.queue_starts(env, k, t, seed_in)

            self._starts = jax.jit(starts, out_shardings=sharding.replicated(self.mesh))
            # the carry is donated: each round updates it in place; unused inputs are kept, so a
            # call hands over its arguments as they are (a pruned input costs every call more)
            jit = functools.partial(jax.jit, keep_unused=True)

            def jitted(loop):
                return rollout.QueueLoop(jit(loop.first), tuple(map(jit, loop.stages)),
                                         jit(loop.turn, donate_argnums=1))
            self._loop = jitted(rollout.queue_loop(env, policy, num_envs, bound, constrain=constrain,
                                                   tail_slots=tail_envs))

            if tail_envs:
                self._tail = jitted(rollout.queue_loop(env, policy, tail_envs, bound, constrain=constrain))
        self._compiled, self.compile_seconds = None, 0.0
        # seconds by stage: trace (Python), lower (to MLIR), xla (or its cache load); store
        # (keying, and loading or saving the executable) where a store is used. A static batch:
        # its one program's. A queue: each program's, as `{program}_{stage}`, and compile_seconds
        # the wall time (the XLA compiles overlap); a tail's as `tail_{program}_{stage}`, and
        # tail_wait: how long the run waited for them, compiled in the background as the head ran.
        self.compile_split: dict[str, float] = {}
        self.store = store if store is not None and executable_store.supported() else None
        # what names a program in the store; the starts (resets) and an env stage's program (the
        # physics) read no policy, so the env, its sharding and their inputs' shapes name them
        self._env_identity = {"env": env.config, "tasks": env.tasks, "devices": [d.id for d in self.mesh.devices.flat],
                              **({"compiler_options": self._options} if self._options else {})}
        self._identity = {**self._env_identity, "caller": None if store is None else store.identity,
                          "policy": policy.name, "meta": policy.meta, "num_envs": num_envs, "queue": self.queue,
                          "seed": seed, "tail_envs": tail_envs, "max_steps": max_steps}
        self._tail_compiled = self._tail_future = self._starts_compiled = self._carry_info = self._starts_info = None
        self.last_wait = 0.0  # seconds the last call waited for the tail's compile (counted as compile)

    def inputs(self, task_ids: np.ndarray, episodes: np.ndarray, n_valid: int | None = None, seed: int = 0) -> tuple:
        """Device inputs for episodes (task_ids[i], episodes[i]), both [queue], of which the
        first `n_valid` (default all) are run; the rest pad the static shape. `seed` is used
        only by a rollout built with seed=None (else its own seed is part of the program)."""
        if len(task_ids) != self.queue:
            raise ValueError(f"expected {self.queue} episodes, got {len(task_ids)}")
        keys = np.asarray(self.env.initial_state_keys(task_ids, episodes, split="eval"))  # [Q, 2]
        queue = (keys, np.asarray(task_ids, np.int32))
        queue = sharding.shard_batch(self.mesh, queue) if self.queue == self.num_envs else \
            sharding.replicate(self.mesh, queue)
        n = np.int32(self.queue if n_valid is None else n_valid)
        seed_in = (sharding.replicate(self.mesh, np.int32(seed)),) if self.seed_input else ()
        return (self.params, *queue, sharding.replicate(self.mesh, n), *seed_in)

    @property
    def compiled(self) -> bool:
        return self._compiled is not None

    def compile(self, inputs: tuple) -> None:
        """Compiles (or loads) the programs for `inputs`. A queue's several are traced and
        lowered here, one after another (the physics patches tracing runs under are
        process-wide), then compiled by XLA side by side in the background. With a tail,
        starts the tail's compile in the background (`__call__` waits for it once the head
        has run)."""
        if self._compiled is not None:
            return
        if self._loop is None:
            self._compiled, self.compile_split = self._compile(self._run, inputs, "all")
            self.compile_seconds = sum(self.compile_split.values())
            return
        t0 = time.perf_counter()
        starts_in = self._starts_inputs(inputs)  # the resets: the env's and the seed's alone, as the physics
        staged = {"starts": self._lower(self._starts, starts_in, "starts", key_inputs=_shapes(starts_in),
                                        identity={**self._env_identity, "seed": self._identity["seed"]})}
        self._starts_info = staged["starts"].out_info
        self._carry_info = self._lower_loop(self._loop, "", self.num_envs, inputs, (), staged)
        done, self.compile_split = self._finish_loop(self._loop, "", staged)
        self._starts_compiled, self._compiled = done["starts"], done["loop"]
        self.compile_seconds = time.perf_counter() - t0
        if self._tail:
            self._tail_future = _COMPILER.submit(self._compile_tail, inputs)

    def _lower_loop(self, loop: rollout.QueueLoop, prefix: str, slots: int, inputs: tuple, carry: tuple,
                    staged: dict):
        """Traces and lowers the programs of `loop` (`slots` env slots) into `staged` (parts
        `{prefix}first`, each stage's name, `{prefix}turn`), `first` given `carry` (a tail's:
        the head's final carry's placed shapes, of num_envs slots; else none); returns `first`'s
        carry's shapes, placed as the next programs take them.
        An env stage's XLA (the physics', the longest of a rollout's) starts at once, beside
        the tracing left, so that it ends that much sooner; the others wait for `_finish_loop`."""
        params, n_valid = inputs[0], inputs[3]

        def lowered(part, fn, args, start=False, **key):
            st = self._lower(fn, args, prefix + part, **key)
            staged[prefix + part] = _COMPILER.submit(self._finish, st, prefix + part) if start else st
            return sharding.slot_specs(self.mesh, st.out_info, slots)

        c, x, go = lowered("first", loop.first, (params, self._starts_info, n_valid, *carry), key_inputs=inputs)
        for stage in loop.stages:  # the env's alone: keyed by the env and its inputs, not the policy
            args = (rollout.queue_states(c), x)
            x = lowered(stage.__name__, stage, args, start=True, identity=self._env_identity, key_inputs=_shapes(args))
        lowered("turn", loop.turn, (params, c, x, go, self._starts_info, n_valid), key_inputs=inputs)
        return c

    def _finish_loop(self, loop: rollout.QueueLoop, prefix: str, staged: dict) -> tuple[dict, dict]:
        """XLA for every program in `staged` not yet started, side by side, after all are traced:
        compiles beside the tracing slow it (on a GPU host XLA's code generation takes every
        core), and the largest compile outlasts it anyway. Returns ({"loop": `loop` compiled,
        each other part: its program}, seconds by `{part}_{stage}`)."""
        futures = {part: st if isinstance(st, concurrent.futures.Future) else _COMPILER.submit(self._finish, st, part)
                   for part, st in staged.items()}
        done, split = {}, {}
        for part, future in futures.items():
            done[part], secs = future.result()
            split.update({f"{part}_{k}": v for k, v in secs.items()})
        programs = [done.pop(prefix + n) for n in ("first", *(f.__name__ for f in loop.stages), "turn")]
        return {"loop": rollout.QueueLoop(programs[0], tuple(programs[1:-1]), programs[-1]), **done}, split

    @staticmethod
    def _starts_inputs(inputs: tuple) -> tuple:
        """The starts program's inputs (keys, task ids[, seed]) of the rollout's inputs."""
        return inputs[1:3] + inputs[4:]

    def _compile(self, fn, inputs: tuple, part: str, key_inputs: tuple | None = None):
        """(compiled `fn` for `inputs`, its seconds by stage); loaded from or saved to the store
        under this rollout's identity, `part` and `key_inputs` (default: `inputs`)."""
        return self._finish(self._lower(fn, inputs, part, key_inputs), part)

    def _lower(self, fn, inputs: tuple, part: str, key_inputs: tuple | None = None,
               identity: dict | None = None) -> executable_store.Staged:
        """`fn`'s program for `inputs` loaded from the store, or traced and lowered; stored
        under `identity` (default this rollout's), `part` and `key_inputs` (default `inputs`)."""
        with jax.set_mesh(self.mesh):  # the env's kernels split their batch as the envs are split
            return executable_store.stage(self.store, {**(identity or self._identity), "part": part}, fn, inputs,
                                          key_inputs)

    def _finish(self, staged: executable_store.Staged, part: str):
        """(`staged`'s program compiled by XLA, or as loaded, and saved to the store; its seconds by stage)."""
        return executable_store.finish(self.store, staged, self._options, on_compiled=lambda: sharding.sync(
            f"heisd_jax.harness.evaluator: rollout {part} compiled"))  # several hosts: the slowest counts

    def _compile_tail(self, inputs: tuple):
        """The tail's programs, traced in turn in this (background) thread, then compiled side by side."""
        staged = {}
        self._lower_loop(self._tail, "tail_", self._tail_envs, inputs, (self._carry_info,), staged)
        done, split = self._finish_loop(self._tail, "tail_", staged)
        return done["loop"], split

    def wait_compiled(self) -> None:
        """Waits for a tail's background compile; its seconds join compile_split as `tail_*`."""
        if self._tail_compiled is None and self._tail_future is not None:
            self._tail_compiled, split = self._tail_future.result()
            self.compile_split.update(split)

    def __call__(self, inputs: tuple, each_round: Callable[[tuple], None] | None = None
                 ) -> tuple[rollout.EpisodeResults, int]:
        """Host copies of (per-episode results [queue], control steps the loop ran).
        `each_round(carry)`: a queue's host-driven rounds, each (`rollout.drive_queue`)."""
        self.compile(inputs)
        self.last_wait = 0.0
        if self._loop is None:
            return sharding.fetch(self._compiled(*inputs))
        params, n_valid = inputs[0], inputs[3]
        starts = self._starts_compiled(*self._starts_inputs(inputs))
        carry = rollout.drive_queue(self._compiled, params, starts, n_valid, each_round=each_round)
        if self._tail is None:
            return sharding.fetch((carry[-1], carry[0]))
        jax.block_until_ready(carry)
        t0 = time.perf_counter()
        waited = self._tail_compiled is None
        self.wait_compiled()
        self.last_wait = time.perf_counter() - t0
        if waited:  # what the tail's compile added to the wall time
            self.compile_split["tail_wait"] = self.last_wait
            self.compile_seconds += self.last_wait
        carry = rollout.drive_queue(self._tail_compiled, params, starts, n_valid, carry=carry, each_round=each_round)
        return sharding.fetch((carry[-1], carry[0]))


def evaluate(env: TabletopEnv, policy: rollout.Policy, cfg: EvalConfig, done: dict[str, list] | None = None,
             on_batch: Callable[[dict[str, list], dict], None] | None = None, seed: int = 0,
             devices: Sequence[jax.Device] | None = None, tasks: Collection[str] | None = None,
             rollouts: dict | None = None, store: executable_store.ExecutableStore | None = None,
             on_progress: Callable[[dict[str, list], dict], None] | None = None,
             stop: Callable[[], bool] | None = None) -> dict[str, list]:
    """Runs every pending episode; returns task name -> per-episode records
    {"success": bool, "steps": int, "failure": str|None, "decode": {stat: total}}, the
    decode totals summed over the episode's actions (e.g. target_passes). The env slots are
    sharded over `devices` (default: all; `num_envs` must be a multiple of their number).
    With `cfg.refill` every pending episode goes into one call, a finished env taking the
    next one; without, or across several processes, batches of `num_envs` episodes run one
    after another.
    `on_batch(results, timing)` is called after every call with everything so far; timing
    holds the call's wall-clock (compilation excluded, reported once as compile_seconds),
    its control steps (iterations of the batched loop: one batched action each), env steps
    and the number of devices. `on_progress(results, timing)`: within a refilled call, every
    `cfg.save_every_s` seconds, everything so far with the episodes that have ended (a
    record is written once an episode ends, so a run saved this way and resumed runs only
    the rest; each episode ends as it would in one run, its reset and keys being its own),
    and the running call's timing so far, as `on_batch`'s with `episodes` those ended (a run
    killed outright keeps the speed of its last save).
    `stop()`, asked after every queue round and before every call: when it says True, the
    episodes that have ended are recorded and handed to `on_progress` (with a refilled queue),
    and `EvaluationStopped` is raised; a resumed run then runs only the rest. Asked between
    rounds, where the round's carry is still the host's to read (each round is given the
    last one's buffers), so a signal handler should only set what `stop` reads.
    `tasks` (names) runs only those of the env's tasks: task ids are data, so an env over
    several suites evaluates each with one program. `rollouts`, a dict the caller keeps for
    this env and policy, holds the compiled rollouts for reuse by later calls of the same
    shapes (no tracing, no compile: `compile_seconds` is then 0); their seed is an input, so
    calls of every seed share them (the same policy keys as a program built for the seed).
    `store`: where compiled rollouts are loaded from and saved to (`BatchRollout`)."""
    results = {k: list(v) for k, v in (done or {}).items()}
    todo = pending_episodes(env, cfg, results, tasks)
    if not todo:
        return results
    run, calls = _plan(env, policy, cfg, todo, seed, devices, rollouts, store)
    reused = run.compiled  # compiled by an earlier call: nothing to report as this call's compile

    def record(out: rollout.EpisodeResults, chunk, rows) -> None:
        for i in rows:
            t, e = chunk[i]
            name = env.tasks[t].name
            rec = results.setdefault(name, [None] * cfg.episodes_per_task)
            rec += [None] * (cfg.episodes_per_task - len(rec))
            failure = None
            if out.invalid_action[i]:
                failure = "invalid_action"
            elif out.unstable[i]:
                failure = "unstable"
            elif not out.success[i]:
                failure = "timeout"
            rec[e] = {"success": bool(out.success[i]), "steps": int(out.steps[i]), "failure": failure,
                      "decode": {k: float(v[i]) for k, v in out.totals.items()}}

    def saver(chunk, call_timing):
        """`each_round` for one call: every `cfg.save_every_s` seconds (0: never), and when
        `stop()` says so, the episodes of `chunk` that have ended since the last save recorded
        and handed to `on_progress` with the call's share so far; then, if stopping,
        `EvaluationStopped` with that share."""
        saved, last = np.zeros(len(chunk), bool), time.perf_counter()

        def share(c, out, slot_ep, ended) -> dict:
            """`on_batch`'s timing for the call so far: its rounds, its ended episodes, and
            the env steps of those and of the running ones."""
            loop_steps, steps = sharding.fetch((c[0], rollout.queue_states(c).step))
            running = np.asarray(slot_ep) < out.steps.shape[0]
            return {**call_timing(), "control_steps": int(loop_steps), "episodes": int(ended.sum()),
                    "env_steps": int(out.steps[:len(chunk)][ended].sum() + np.asarray(steps)[running].sum())}

        def each_round(c):
            nonlocal last
            stopping = stop is not None and stop()
            due = on_progress is not None and cfg.save_every_s > 0 and time.perf_counter() - last >= cfg.save_every_s
            if not (stopping or due):
                return
            next_ep, slot_ep, out = sharding.fetch((c[2], c[3], c[-1]))  # waits for this round
            ended = rollout.ended_episodes(next_ep, slot_ep, out.steps.shape[0])[:len(chunk)]
            if on_progress is not None and (ended & ~saved).any():
                record(out, chunk, np.flatnonzero(ended & ~saved))
                saved[ended] = True
                on_progress(results, share(c, out, slot_ep, ended))
            last = time.perf_counter()
            if stopping:
                raise EvaluationStopped(results, share(c, out, slot_ep, ended))
        return each_round

    for chunk, inputs in calls:
        if stop is not None and stop():
            raise EvaluationStopped(results)
        run.compile(inputs)  # ahead of time, so call timings exclude compilation
        t0 = time.perf_counter()
        progressing = stop is not None or (on_progress is not None and cfg.save_every_s > 0)

        def call_timing() -> dict:
            return {"batch_seconds": time.perf_counter() - t0 - run.last_wait,  # a wait for the tail's compile
                    "compile_seconds": 0.0 if reused else run.compile_seconds,   # counts as compile
                    "compile_split": {} if reused else run.compile_split, "devices": run.devices}
        out, loop_steps = run(inputs, saver(chunk, call_timing) if progressing else None)
        timing = call_timing()
        record(out, chunk, range(len(chunk)))
        if on_batch is not None:
            on_batch(results, {**timing, "episodes": len(chunk), "control_steps": int(loop_steps),
                               "env_steps": int(np.sum(out.steps[:len(chunk)]))})
    return results


def compile_rollout(env: TabletopEnv, policy: rollout.Policy, cfg: EvalConfig, done: dict[str, list] | None = None,
                    seed: int = 0, devices: Sequence[jax.Device] | None = None,
                    store: executable_store.ExecutableStore | None = None) -> dict[str, float]:
    """Compiles the program `evaluate` would run for the pending episodes (filling JAX's
    persistent compilation cache, where on) and runs nothing; returns its compile seconds:
    trace, lower, xla (their tail_* twins for a tail's program, compiled alongside), store
    where used, and total (wall). {} when no episode is pending."""
    todo = pending_episodes(env, cfg, done or {})
    if not todo:
        return {}
    run, calls = _plan(env, policy, cfg, todo, seed, devices, store=store)
    t0 = time.perf_counter()
    run.compile(next(calls)[1])
    run.wait_compiled()
    return {**run.compile_split, "total": time.perf_counter() - t0}


def _plan(env, policy, cfg, todo, seed, devices, rollouts=None, store=None):
    """The rollout for `todo` (pending (task, episode) pairs) and a generator of its calls:
    (episodes, device inputs), each call's episodes padded to the program's static queue."""
    refill = cfg.refill and jax.process_count() == 1  # several hosts: batches (refilling is tested on one host)
    if refill:  # longest episodes first, so the queue does not end on a slot that just began a long one
        todo = sorted(todo, key=lambda te: -int(env.tasks[te[0]].max_steps))
    per_call = -(-len(todo) // cfg.num_envs) * cfg.num_envs if refill else cfg.num_envs
    tail = cfg.tail_envs if refill else 0
    key = (cfg.num_envs, per_call, tail, None if devices is None else tuple(d.id for d in devices), cfg.deterministic)
    run = (rollouts or {}).get(key)
    if run is None:
        run = BatchRollout(env, policy, cfg.num_envs, None if rollouts is not None else seed, devices, queue=per_call,
                           tail_envs=tail, store=store, deterministic=cfg.deterministic)
        if rollouts is not None:
            rollouts[key] = run

    def calls():
        for start in range(0, len(todo), per_call):
            chunk = todo[start: start + per_call]
            pad = chunk + [chunk[-1]] * (per_call - len(chunk))  # static shape
            tids, eps = np.array(pad).T
            yield chunk, run.inputs(tids, eps, n_valid=len(chunk), seed=seed)
    return run, calls()


def _decode_means(recs: list[dict]) -> dict:
    """Decoding statistics of a set of episodes: every decode total divided by the number of
    actions taken (e.g. target passes per action), target passes per episode, and the episodes
    that decoded an invalid observation."""
    actions = sum(r["steps"] for r in recs)
    keys = set().union(*(r.get("decode", {}) for r in recs))
    out = {f"{k}_per_action": sum(r.get("decode", {}).get(k, 0.0) for r in recs) / max(actions, 1)
           for k in sorted(keys)}
    if "target_passes" in keys:  # what an episode costs: a method that lengthens episodes pays here
        out["target_passes_per_episode"] = sum(r["decode"].get("target_passes", 0.0) for r in recs) / len(recs)
    if "tokens" in keys and "target_passes" in keys:  # acceptance length: tokens per target pass
        passes = sum(r["decode"].get("target_passes", 0.0) for r in recs)
        out["tokens_per_target_pass"] = sum(r["decode"].get("tokens", 0.0) for r in recs) / max(passes, 1e-9)
    if "invalid" in keys:  # episodes that met an observation the model cannot read (vla.mark_invalid)
        out["invalid_episodes"] = sum(r["decode"].get("invalid", 0.0) > 0 for r in recs)
    return out


def summarize(env_tasks: tuple[tasks_lib.Task, ...], results: dict[str, list]) -> dict:
    """Success rates and per-action decoding statistics per task and per suite (over
    finished episodes)."""
    per_task, per_suite = {}, {}
    for task in env_tasks:
        recs = [r for r in results.get(task.name, []) if r is not None]
        if not recs:
            continue
        sr = float(np.mean([r["success"] for r in recs]))
        per_task[task.name] = {"suite": task.suite, "episodes": len(recs), "success_rate": sr,
                               "mean_steps": float(np.mean([r["steps"] for r in recs])), **_decode_means(recs)}
        per_suite.setdefault(task.suite, []).extend(recs)
    suites = {}
    for name, recs in per_suite.items():
        n_succ = int(sum(r["success"] for r in recs))
        suites[name] = {"episodes": len(recs), "successes": n_succ, "success_rate": n_succ / len(recs),
                        "mean_steps": float(np.mean([r["steps"] for r in recs])), **_decode_means(recs)}
    return {"tasks": per_task, "suites": suites}
