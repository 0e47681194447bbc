"""Policy-in-the-loop rollouts: one jitted function, control steps under a loop, envs batched.

A policy is a pair of pure *batched* functions over the env batch [B]:
`init(params, states) -> policy_state` and
`act(params, states, policy_state, keys) -> (actions [B, 7], policy_state, stats)`,
where `stats` is a dict of per-env numbers describing this action's decoding (target
passes, accepted tokens, ...; empty for the expert). The rollout sums them over the steps
each env was still running. Batched (rather than per-env) so that a decode step can act on
the whole batch: skip a model call no row needs, gather rows into buckets. `per_env` wraps
a per-env policy by vmapping it. `params` (model weights, any pytree) travel as an argument
of the jitted rollout rather than as baked-in constants. Finished envs are frozen by the
environment itself.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any, Callable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.env import EnvState, TabletopEnv

Stats = dict[str, jnp.ndarray]


@dataclasses.dataclass(frozen=True)
class Policy:
    name: str
    init: Callable[[Any, EnvState], Any]
    act: Callable[[Any, EnvState, Any, jax.Array], tuple[jnp.ndarray, Any, Stats]]
    params: Any = None
    meta: dict = dataclasses.field(default_factory=dict)  # what built it (model config, method config), for tools


def per_env(name: str, init: Callable[[EnvState], Any], act: Callable[[EnvState, Any, jax.Array], tuple]) -> Policy:
    """A batched Policy from per-env `init(state)` and `act(state, pstate, key) -> (action, pstate)`."""
    def act_b(params, states, pstate, keys):
        actions, pstate = jax.vmap(act)(states, pstate, keys)
        return actions, pstate, {}

    return Policy(name=name, init=lambda params, states: jax.vmap(init)(states), act=act_b)


def seeded_keys(act_keys: jax.Array, seed: int | jax.Array) -> jax.Array:
    """The policy's episode keys [B, 2] under `seed`: folded with it, except that seed 0 keeps
    the historical keys. `seed` is a Python int (one program per seed) or a traced int32
    scalar (one program for every seed; the same keys)."""
    if isinstance(seed, int) and seed == 0:
        return act_keys
    folded = jax.vmap(lambda k: jax.random.fold_in(k, seed))(act_keys)
    return folded if isinstance(seed, int) else jnp.where(seed == 0, act_keys, folded)


class QueueStarts(NamedTuple):
    """What starts each episode of a queue: its initial env state and its policy key, [N, ...]."""
    states: EnvState
    act_keys: jax.Array


def queue_starts(env: TabletopEnv, keys: jax.Array, task_ids: jnp.ndarray, seed: int | jax.Array = 0) -> QueueStarts:
    """The initial states and policy keys of episodes (keys [N, 2] initial-state keys, task_ids
    [N]), as `run_episodes` starts them. A function of its own so that `run_queue` can take
    them from a program compiled apart (and beside) its loop's."""
    reset_keys, act_keys = jax.vmap(lambda k: jax.random.split(k))(keys).transpose(1, 0, 2)
    return QueueStarts(jax.vmap(env.reset)(reset_keys, task_ids), seeded_keys(act_keys, seed))


def _start(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray, seed: int | jax.Array = 0):
    """Reset envs and policy state for episodes (keys [B, 2], task_ids [B])."""
    state, act_keys = queue_starts(env, keys, task_ids, seed)
    return state, policy.init(policy.params, state), act_keys


def _act(policy: Policy, state, pstate, act_keys, t):
    """The policy's batched action; each env's key is its episode key folded with its own
    step count (the loop counter `t` where all envs started together), so an episode's
    keys do not depend on when or in which slot it started."""
    if t is None:
        k = jax.vmap(jax.random.fold_in)(act_keys, state.step)
    else:
        k = jax.vmap(lambda k: jax.random.fold_in(k, t))(act_keys)
    return policy.act(policy.params, state, pstate, k)


def _stats_shape(policy: Policy, state, pstate, act_keys) -> Stats:
    _, _, stats = jax.eval_shape(lambda: _act(policy, state, pstate, act_keys, 0))
    return {k: jnp.zeros(v.shape, jnp.float32) for k, v in stats.items()}


def run_episodes(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray,
                 max_steps: int, seed: int = 0) -> tuple[EnvState, Stats, jnp.ndarray]:
    """Runs a batch of episodes to the end (all done, or `max_steps`).
    `keys` [B, 2] are initial-state keys (see TabletopEnv.initial_state_keys); `seed` only
    changes the keys handed to the policy (the initial states stay the fixed ones, as in
    LIBERO; deterministic policies such as greedy decoding ignore it). Returns the
    final states, the policy's decode statistics summed per env over its running steps
    (dict of [B]), and the number of control steps the batch loop ran."""
    state, pstate, act_keys = _start(env, policy, keys, task_ids, seed)
    totals = _stats_shape(policy, state, pstate, act_keys)

    def cond(c):
        t, state, _, _ = c
        return (t < max_steps) & ~jnp.all(state.done)

    def body(c):
        t, state, pstate, totals = c
        action, pstate, stats = _act(policy, state, pstate, act_keys, t)
        running = ~state.done
        totals = {k: totals[k] + jnp.where(running, stats[k], 0.0) for k in totals}
        return t + 1, jax.vmap(env.step)(state, action), pstate, totals

    t, state, _, totals = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), state, pstate, totals))
    return state, totals, t


def host_loop(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray,
              seed: int = 0) -> Iterator[EnvState]:
    """The batch's state before each control step of the episodes `run_episodes` runs (keys
    [B, 2], task_ids [B]), one jitted control step per iteration from the host: for analyses
    that read every step there. Endless; finished envs freeze."""
    state, pstate, act_keys = jax.jit(lambda k, t: _start(env, policy, k, t, seed))(keys, jnp.asarray(task_ids))

    @jax.jit
    def step(state, pstate, act_keys, t):
        action, pstate, _ = _act(policy, state, pstate, act_keys, t)
        return jax.vmap(env.step)(state, action), pstate

    for t in itertools.count():
        yield state
        state, pstate = step(state, pstate, act_keys, jnp.int32(t))


def record_eval_starts(env: TabletopEnv, policy: Policy, n_envs: int, n_steps: int):
    """`record_episodes` of `policy` in n_envs envs cycling through the env's fixed evaluation
    initial states (`TabletopEnv.cycling_eval_starts`), one jitted call, brought to the host.
    Returns (task ids [n_envs], the trajectory dict of [n_steps, n_envs, ...] numpy arrays)."""
    tids, keys = env.cycling_eval_starts(n_envs)
    run = jax.jit(lambda p, k, t: record_episodes(env, dataclasses.replace(policy, params=p), k, t, n_steps))
    _, traj = jax.device_get(run(policy.params, keys, jnp.asarray(tids, jnp.int32)))
    return tids, traj


def record_episodes(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray, n_steps: int,
                    exec_noise: float = 0.0, teacher: Policy | None = None, beta: float | jax.Array = 0.0,
                    limit: jax.Array | int | None = None):
    """Like run_episodes for exactly `n_steps`, also returning the trajectory: a dict of
    [n_steps, B, ...] arrays (observation before each action, the action, ee kinematics,
    done, and the policy's per-step decode statistics under "stats").

    limit: run only the first min(limit, n_steps) control steps (a traced int: the rows after
    it stay zero). One compiled program then serves batches of every time limit up to
    `n_steps`, where a static `n_steps` per limit compiles one program each; each step is
    the same computation either way. `beta` may be traced too, so one program serves every
    DAgger round's mixture.

    exec_noise: std of Gaussian noise added to the six motion dimensions of the *executed*
    action only; the recorded action is the policy's own (noise injection as in DART: more
    diverse states, clean labels).

    teacher: DAgger (Ross et al. 2011). The teacher acts alongside on every state the
    rollout visits, and its action is the recorded label ("action"; the policy's own is
    under "policy_action"); each env executes the teacher's action with probability
    `beta` per step and the policy's otherwise, so the states are the policy's. The
    teacher's own per-step stats are under "teacher_stats" (e.g. `expert.observer`'s phase)."""
    state, pstate, act_keys = _start(env, policy, keys, task_ids)
    tstate = None if teacher is None else teacher.init(teacher.params, state)

    def body(carry, t):
        state, pstate, tstate = carry
        action, pstate, stats = _act(policy, state, pstate, act_keys, t)
        out = dict(stats=stats, image=state.obs.image, proprio=state.obs.proprio, action=action, ee_vel=state.kin.lin_vel,
                   ee_ang_vel=state.kin.ang_vel, ee_acc=state.kin.lin_acc, gripper_vel=state.kin.gripper_vel,
                   done=state.done)
        step_keys = jax.vmap(lambda k: jax.random.fold_in(k, t))(act_keys)
        executed = action
        if teacher is not None:
            label, tstate, tstats = teacher.act(teacher.params, state, tstate,
                                                jax.vmap(lambda k: jax.random.fold_in(k, 2))(step_keys))
            take = jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, 3)) < beta)(step_keys)
            executed = jnp.where(take[:, None], label, action)
            out.update(action=label, policy_action=action, teacher_stats=tstats)
        noise = exec_noise * jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(k, 1), (6,)))(step_keys)
        executed = executed.at[:, :6].set(jnp.clip(executed[:, :6] + noise, -1.0, 1.0))
        return (jax.vmap(env.step)(state, executed), pstate, tstate), out

    carry = (state, pstate, tstate)
    if limit is None:
        (state, _, _), traj = jax.lax.scan(body, carry, jnp.arange(n_steps))
        return state, traj

    def step_into(t, c):  # one step, its records written into row t of the buffers
        carry, bufs = c
        carry, out = body(carry, t)
        return carry, jax.tree.map(lambda b, o: jax.lax.dynamic_update_index_in_dim(b, o, t, 0), bufs, out)

    rows = jax.eval_shape(lambda c: body(c, jnp.zeros((), jnp.int32))[1], carry)
    bufs = jax.tree.map(lambda r: jnp.zeros((n_steps, *r.shape), r.dtype), rows)
    (state, _, _), traj = jax.lax.fori_loop(0, jnp.minimum(limit, n_steps), step_into, (carry, bufs))
    return state, traj


class EpisodeResults(NamedTuple):
    """Per-episode outcomes, each [N]: of a batch's envs, or of `run_queue`'s episode queue."""
    success: jnp.ndarray
    steps: jnp.ndarray
    invalid_action: jnp.ndarray
    unstable: jnp.ndarray
    totals: Stats  # the policy's decode statistics summed over the episode's steps

    @classmethod
    def of(cls, state: EnvState, totals: Stats) -> "EpisodeResults":
        """The outcomes a batch of (final) env states and their decode totals record."""
        return cls(state.success, state.step, state.invalid_action, state.unstable, totals)


def per_row_leaves(policy: Policy, states: Any) -> Any:
    """Which leaves of `policy.init`'s state are batched over the envs: a pytree of bools,
    True where a leaf's leading dimension follows the batch size of `states` (concrete or
    shapes only). Found by tracing `init` at that batch size and at one more, so a batch-wide
    leaf (e.g. one entry per draft option) is told apart from a per-env one even when its
    length equals the batch size."""
    more = jax.tree.map(lambda x: jax.ShapeDtypeStruct((x.shape[0] + 1,) + x.shape[1:], x.dtype), states)
    at_b, at_more = (jax.eval_shape(lambda st: policy.init(policy.params, st), st) for st in (states, more))
    return jax.tree.map(lambda a, b: a.shape != b.shape, at_b, at_more)


def rows_set(rows: jnp.ndarray, new: Any, old: Any, per_row: Any = True,
             shared_too: jnp.ndarray | bool = False) -> Any:
    """Writes `new`'s rows [R] into `old`'s rows `rows` [R] (an index past the batch: dropped)
    for every leaf that `per_row` (a pytree of bools as `per_row_leaves` gives, or one bool
    for all leaves) marks as batched over the envs; the other (batch-wide) leaves keep `old`,
    or take `new`'s where `shared_too` holds."""
    if isinstance(per_row, bool):
        per_row = jax.tree.map(lambda _: per_row, old)

    def put(o, nw, row):
        return o.at[rows].set(nw, mode="drop") if row else jnp.where(shared_too, nw, o)
    return jax.tree.map(put, old, new, per_row)


def replay_lanes(running: np.ndarray, envs: int, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """Replay indices (steps [T, batch], envs [T, batch]) into a recording whose running mask
    is `running` [steps, recorded envs]: lane j plays the running steps of envs j, j + batch,
    ... (of the first `envs`) one after another; every lane is cut to the shortest, T."""
    if not np.all(running[:-1] >= running[1:]):
        raise ValueError("an env runs again after its episode ended: the recording is not one episode per env")
    n = running.sum(0)
    per_lane = [[(t, e) for e in range(j, envs, batch) for t in range(n[e])] for j in range(batch)]
    t_len = min(len(lane) for lane in per_lane)
    if t_len == 0:
        raise ValueError(f"a lane of batch {batch} has no running step: record more envs or steps")
    idx = np.asarray([lane[:t_len] for lane in per_lane]).transpose(1, 0, 2)  # [T, batch, 2]
    return idx[..., 0], idx[..., 1]


def run_queue(env: TabletopEnv, policy: Policy, keys: jax.Array | None, task_ids: jnp.ndarray | None,
              n_valid: jnp.ndarray, num_slots: int, max_steps: int, seed: int = 0, refills_per_step: int | None = None,
              constrain: Callable[[Any, int], Any] = lambda tree, n: tree,
              tail_slots: int = 0, split: bool = False, starts: QueueStarts | None = None
              ) -> tuple[EpisodeResults, jnp.ndarray] | tuple:
    """Runs the first `n_valid` episodes of a queue (`keys` [N, 2] initial-state keys and
    `task_ids` [N], N static) in `num_slots` envs: when an env's episode ends, its outcome
    is written to the episode's row and the slot takes the next pending episode, so no env
    waits for the slowest episode of a batch and the loop runs until the queue is empty and
    every slot has finished. The episodes' starts are `queue_starts(env, keys, task_ids,
    seed)`, computed once before the loop, or `starts` where given (then keys, task_ids and
    seed are not read): the loop itself holds no env reset, and a caller can compile the
    starts as a program of their own, beside the loop's. `queue_loop` gives the same loop as
    programs for a host to drive.

    An episode's trajectory is the one `run_episodes` gives it (same reset, same policy
    keys), whichever slot and step it starts at, for policies whose rows do not interact.
    At most `refills_per_step` slots (default num_slots // 8, at least 1) restart per
    loop iteration, so a refill resets a few envs rather than the whole batch; a finished
    slot beyond that waits a step. The slots start empty and the same refill fills them
    before the first control step (num_slots / refills_per_step iterations that step
    nothing). Batch-wide policy-state leaves (not per slot) take the first refill's initial
    values and are kept after. `max_steps`
    bounds the loop's control steps (the whole queue), not an episode (each task's own
    limit ends its episodes). `constrain(tree, n)` applies a sharding constraint to the
    carry of n slots (identity on one device).

    `tail_slots` (0 < tail_slots < num_slots; 0: off): once the queue is empty and at most
    that many slots still run, those slots are gathered into a batch of `tail_slots` and the
    loop goes on at that size. The queue's tail (the last, longest episodes, often
    failures running to their task's limit) then no longer pays a full batch's step for a
    few live envs. The program holds a second copy of the control step, at the tail's
    size (a longer compile); an episode's steps are the same at either size wherever the
    policy's and env's per-row arithmetic does not depend on the batch size. Batch-wide
    policy-state leaves are kept as they are. `split` (with `tail_slots`): return the loop's
    carry where the tail starts, for `run_queue_tail` in a program of its own. Returns the
    per-episode results and the number of control steps the loop ran."""
    s = num_slots
    _check_tail(s, tail_slots)
    starts = queue_starts(env, keys, task_ids, seed) if starts is None else starts
    n_queue = starts.act_keys.shape[0]
    n_valid = jnp.asarray(n_valid, jnp.int32)
    refill, refill_due = _queue_refill(policy, starts, n_valid, s, refills_per_step)
    step, cond = _queue_step(env, policy, n_queue), _queue_cond(max_steps, n_valid, n_queue, tail_slots)

    def body(c):
        c = jax.lax.cond(refill_due(c), refill, lambda c: c, c)
        c = jax.lax.cond(c[1] >= s, step, lambda c: c, c)  # control steps once every slot is set
        return _constrain_carry(c, constrain, s)

    c = jax.lax.while_loop(cond, body, _queue_carry(policy, starts, s, constrain))
    if tail_slots == 0:
        return c[-1], c[0]
    if split:
        return c
    return run_queue_tail(env, policy, c, n_valid, max_steps, tail_slots, constrain)


class QueueLoop(NamedTuple):
    """`run_queue`'s loop as pure functions for a host to drive, each a program of its own
    (XLA compiles them in parallel), the env's step split at its `step_stages`:

        carry, x, go = first(params, starts, n_valid)   # every slot takes an episode; stage 0
        repeat:  x = stage(queue_states(carry), x) for each middle stage       # e.g. the physics
                 carry, x, go, alive = turn(params, carry, x, go, starts, n_valid)
        until alive is False; then carry[-1] holds the results, carry[0] the control steps.

    A round is one control step of `run_queue`'s loop, the same code, every episode ending as
    there: `turn` ends one control step (the last stage, the outcomes of the episodes that
    ended) and begins the next (refill, the policy's action, stage 0), so a round is the
    middle stages and one `turn`. A middle stage reads only the slots' env states, so its
    program is the env's alone, whichever policy runs (the evaluator shares it across
    methods). The slots are filled at once rather than `refills_per_step`
    per iteration (the episodes do not depend on when they start). A round after the loop's
    end (`go` False) leaves the carry as it was, so a host may read `alive` a round late
    (`drive_queue`). No program holds a conditional, which on a GPU would hold the host until
    the device reaches it. With `tail_slots`, `alive` turns False where the tail starts, and
    the carry is `run_queue_tail`'s, and the queue loop of `tail_slots` slots (no tail of its
    own) goes on from it: its `first(params, starts, n_valid, carry)` gathers the running slots
    (`run_queue_tail` as programs; its refills take nothing, the queue being empty)."""
    first: Callable[..., tuple]
    stages: tuple[Callable[[EnvState, Any], Any], ...]
    turn: Callable[[Any, tuple, Any, jnp.ndarray, QueueStarts, jnp.ndarray], tuple]


def queue_loop(env: TabletopEnv, policy: Policy, num_slots: int, max_steps: int, refills_per_step: int | None = None,
               constrain: Callable[[Any, int], Any] = lambda tree, n: tree, tail_slots: int = 0) -> QueueLoop:
    """`run_queue`'s loop (same arguments) as a `QueueLoop`, policy parameters an input. The
    env's step splits at `env.step_stages` where it has them (else one stage, `env.step`)."""
    s = num_slots
    _check_tail(s, tail_slots)
    stages = getattr(env, "step_stages", (env.step,))
    batched = [jax.vmap(f) for f in stages]

    def kept(go, new, old):  # new where the round runs, else old
        return jax.tree.map(lambda n, o: jnp.where(go, n, o), new, old)

    def head(pol, c, starts, n_valid, go):  # refill, act, stage 0; go: whether the loop goes on
        refill, _ = _queue_refill(pol, starts, n_valid, s, refills_per_step)
        c = refill(c, go)  # takes nothing unless a slot is free and an episode pending
        acted, action = _queue_act(pol, c)
        c = c[:5] + kept(go, acted[5:8], c[5:8]) + c[8:]  # the policy's state, keys, totals
        # every output placed (a program's outputs are the next one's inputs, lowered at that placement)
        return constrain((c, batched[0](c[4], action), go), s)

    def first(params, starts, n_valid, carry=None):
        pol = dataclasses.replace(policy, params=params)
        if carry is None:
            fill, _ = _queue_refill(pol, starts, n_valid, s, s)
            c = fill(_queue_carry(pol, starts, s, constrain))
        else:  # a tail: the head's carry where it stopped, its running slots gathered into s
            c = _gather_tail(pol, carry, s, constrain)
        return head(pol, c, starts, n_valid, _queue_cond(max_steps, n_valid, starts.act_keys.shape[0], tail_slots)(c))

    def middle(fn, name):
        def stage(state, x):
            return constrain(fn(state, x), s)
        stage.__name__ = name  # the env's stage's (a program's name in the evaluator)
        return stage

    def turn(params, c, x, go, starts, n_valid):  # the last stage, outcomes; then the next head
        n_queue = starts.act_keys.shape[0]
        state = kept(go, batched[-1](c[4], x) if len(batched) > 1 else x, c[4])
        c = _queue_record(n_queue, c, state, count=go.astype(jnp.int32))
        alive = _queue_cond(max_steps, n_valid, n_queue, tail_slots)(c)
        return *head(dataclasses.replace(policy, params=params), c, starts, n_valid, alive), constrain(alive, s)

    names = [getattr(f, "__name__", f"stage{i}") for i, f in enumerate(stages)]
    return QueueLoop(first=first, stages=tuple(middle(f, n) for f, n in zip(batched[1:-1], names[1:-1])), turn=turn)


def queue_states(carry: tuple) -> EnvState:
    """The env states of a queue loop's slots, in its carry."""
    return carry[4]


def drive_queue(loop: QueueLoop, params: Any, starts: QueueStarts, n_valid: jnp.ndarray, carry: tuple | None = None,
                each_round: Callable[[tuple], None] | None = None) -> tuple:
    """Runs `loop` (its functions, typically compiled) from the host to the end of the queue
    (or where its tail starts); returns the final carry. Each round's `alive` is read after
    the next round is queued, so the device is not left waiting for the host. `carry`: a
    tail's loop goes on from the head's final carry. `each_round(carry)`: called on the host
    with every round's carry as it is queued (reading it waits for the device: a caller that
    saves progress reads it now and then, `ended_episodes`)."""
    c, x, go = loop.first(params, starts, n_valid) if carry is None else loop.first(params, starts, n_valid, carry)
    alive = None
    while True:
        for stage in loop.stages:
            x = stage(queue_states(c), x)
        c, x, go, now = loop.turn(params, c, x, go, starts, n_valid)
        if each_round is not None:
            each_round(c)
        if alive is not None and not bool(alive):
            return c
        alive = now


def ended_episodes(next_ep, slot_ep, n_queue: int) -> np.ndarray:
    """[n_queue] bool on the host, from a queue carry's next_ep and slot_ep (`carry[2:4]`):
    the episodes that have ended, taken from the queue and no longer in a slot. Their rows of
    the carry's results (`carry[-1]`) are final: a slot writes its episode's row once, when
    the episode ends."""
    slot_ep = np.asarray(slot_ep)
    ended = np.arange(n_queue) < int(next_ep)
    ended[slot_ep[slot_ep < n_queue]] = False
    return ended


def _check_tail(num_slots: int, tail_slots: int) -> None:
    if not 0 <= tail_slots < num_slots:
        raise ValueError(f"tail_slots must be 0 (off) or in 1..{num_slots - 1} (below num_slots {num_slots}), "
                         f"got {tail_slots}")


def _queue_carry(policy: Policy, starts: QueueStarts, s: int, constrain: Callable[[Any, int], Any]) -> tuple:
    """The loop's carry before its first iteration: s empty slots (a template, overwritten,
    never stepped), every episode's results zero.
    (t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results)."""
    n_queue = starts.act_keys.shape[0]
    state = jax.tree.map(lambda x: jnp.zeros((s,) + x.shape[1:], x.dtype), starts.states)
    pstate = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype),
                          jax.eval_shape(lambda st: policy.init(policy.params, st), state))
    act_keys = jnp.zeros((s,) + starts.act_keys.shape[1:], starts.act_keys.dtype)
    slot_ep = jnp.full((s,), n_queue, jnp.int32)  # n_queue: an empty slot
    totals = _stats_shape(policy, state, pstate, act_keys)
    results = jax.tree.map(lambda x: jnp.zeros((n_queue,), x.dtype), EpisodeResults.of(state, totals))
    zero = jnp.zeros((), jnp.int32)
    return (zero, zero, zero, *constrain((slot_ep, state, pstate, act_keys, totals), s), results)


def _constrain_carry(c: tuple, constrain: Callable[[Any, int], Any], s: int) -> tuple:
    t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results = c
    return t, blank, next_ep, *constrain((slot_ep, state, pstate, act_keys, totals), s), results


def _queue_refill(policy: Policy, starts: QueueStarts, n_valid: jnp.ndarray, s: int,
                  refills_per_step: int | None) -> tuple[Callable[[tuple], tuple], Callable[[tuple], jnp.ndarray]]:
    """(refill(carry): up to r slots take the next pending episodes, whether one is due)."""
    n_queue = starts.act_keys.shape[0]
    r = max(1, s // 8) if refills_per_step is None else min(refills_per_step, s)
    lanes = jnp.arange(r, dtype=jnp.int32)

    def refill(c, go=True):  # go: a traced bool, False takes nothing
        t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results = c
        per_row = per_row_leaves(policy, state)
        eps = next_ep + lanes
        # Slots still holding the template are set first, in order (episodes past the queue
        # give them a valid, finished state); then the slots whose episode ended.
        free = jnp.nonzero(slot_ep == n_queue, size=r, fill_value=s)[0]
        rows = jnp.where(blank < s, blank + lanes, free)  # [r] slot rows; >= s: none
        take = (rows < s) & (eps < n_valid)
        if go is not True:
            take = take & go
        rows = jnp.where(take | (blank < s), rows, s)
        idx = jnp.minimum(eps, n_queue - 1)
        s2, k2 = jax.tree.map(lambda x: x[idx], tuple(starts))
        p2 = policy.init(policy.params, s2)
        s2 = s2.replace(done=s2.done | ~take)
        state = rows_set(rows, s2, state)
        pstate = rows_set(rows, p2, pstate, per_row, shared_too=blank == 0)
        act_keys = act_keys.at[rows].set(k2, mode="drop")
        totals = {k: v.at[rows].set(0.0, mode="drop") for k, v in totals.items()}
        slot_ep = slot_ep.at[jnp.where(take, rows, s)].set(eps, mode="drop")
        return t, jnp.minimum(blank + r, s), next_ep + jnp.sum(take), slot_ep, state, pstate, act_keys, totals, results

    def due(c):
        blank, next_ep, slot_ep = c[1:4]
        return (blank < s) | (jnp.any(slot_ep == n_queue) & (next_ep < n_valid))

    return refill, due


def run_queue_tail(env: TabletopEnv, policy: Policy, carry: tuple, n_valid: jnp.ndarray, max_steps: int,
                   tail_slots: int, constrain: Callable[[Any, int], Any] = lambda tree, n: tree
                   ) -> tuple[EpisodeResults, jnp.ndarray]:
    """The queue's tail: from the carry `run_queue(..., split=True)` returns (the queue empty,
    at most `tail_slots` slots running), those slots gathered into a batch of `tail_slots`
    and stepped until every episode has ended, as `run_queue` with `tail_slots` returns (a
    queue loop of `tail_slots` slots from this carry, `queue_loop`, runs it as programs a host
    drives)."""
    n_queue = jax.tree.leaves(carry[-1])[0].shape[0]
    step, cond = _queue_step(env, policy, n_queue), _queue_cond(max_steps, n_valid, n_queue)

    def tail_body(c):
        t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results = step(c)
        return t, blank, next_ep, *constrain((slot_ep, state, pstate, act_keys, totals), tail_slots), results

    c = jax.lax.while_loop(cond, tail_body, _gather_tail(policy, carry, tail_slots, constrain))
    return c[-1], c[0]


def _gather_tail(policy: Policy, carry: tuple, tail_slots: int, constrain: Callable[[Any, int], Any]) -> tuple:
    """A queue's carry where its tail starts, its running slots gathered into `tail_slots`."""
    t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results = carry
    n_queue = jax.tree.leaves(results)[0].shape[0]
    keep = jnp.argsort(slot_ep == n_queue, stable=True)[:tail_slots]  # running slots first, then finished ones
    pstate = jax.tree.map(lambda x, row: x[keep] if row else x, pstate, per_row_leaves(policy, state))
    tail = constrain(jax.tree.map(lambda x: x[keep], (slot_ep, state)) + (pstate,) +
                     jax.tree.map(lambda x: x[keep], (act_keys, totals)), tail_slots)
    return t, blank, next_ep, *tail, results


def _queue_act(policy: Policy, c: tuple) -> tuple[tuple, jnp.ndarray]:
    """The policy's action for a queue's slots, its decode statistics added to the running
    slots' totals: (carry, actions)."""
    t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results = c
    action, pstate, stats = _act(policy, state, pstate, act_keys, None)
    running = ~state.done
    totals = {k: totals[k] + jnp.where(running, stats[k], 0.0) for k in totals}
    return (t, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results), action


def _queue_record(n_queue: int, c: tuple, state: EnvState, count: int | jnp.ndarray = 1) -> tuple:
    """The carry after a control step to `state`: the outcome of every episode that ended
    written to its row (a slot's episode index n_queue: empty), `count` added to the steps."""
    t, blank, next_ep, slot_ep, _, pstate, act_keys, totals, results = c
    ended = (slot_ep < n_queue) & state.done
    at = jnp.where(ended, slot_ep, n_queue)  # n_queue: dropped
    results = jax.tree.map(lambda r, x: r.at[at].set(x, mode="drop"), results, EpisodeResults.of(state, totals))
    slot_ep = jnp.where(ended, n_queue, slot_ep)
    return t + count, blank, next_ep, slot_ep, state, pstate, act_keys, totals, results


def _queue_step(env: TabletopEnv, policy: Policy, n_queue: int) -> Callable[[tuple], tuple]:
    """One control step of a queue's slots: act, step the envs, record the episodes that ended."""

    def step(c):
        c, action = _queue_act(policy, c)
        return _queue_record(n_queue, c, jax.vmap(env.step)(c[4], action))

    return step


def _queue_cond(max_steps: int, n_valid: jnp.ndarray, n_queue: int, tail_slots: int = 0
                ) -> Callable[[tuple], jnp.ndarray]:
    """Whether a queue's loop goes on: within `max_steps`, and an episode still runs or is
    pending; with `tail_slots`, also not yet at the tail (the queue empty, at most that many
    slots running)."""

    def cond(c):
        t, blank, next_ep, slot_ep, *_ = c
        go = (t < max_steps) & (jnp.any(slot_ep < n_queue) | (next_ep < n_valid))
        if tail_slots:
            tail = (next_ep >= n_valid) & (jnp.sum(slot_ep < n_queue) <= tail_slots)
            go = go & ~(tail & (blank >= c[3].shape[0]))
        return go

    return cond
