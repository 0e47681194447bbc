"""`rollout.run_queue` (env slots refilled from a queue of episodes) against
`rollout.run_episodes` (one static batch), on a stand-in env whose episodes last a
key-dependent number of steps and whose outcome depends on every action the policy took:
each episode must end exactly as when it runs alone, whichever slot and step it starts at.
Fast (no physics); tests/test_slots.py checks the same on the MJX env with the expert."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from envs import rollout


@struct.dataclass
class _State:
    step: jnp.ndarray
    length: jnp.ndarray
    total: jnp.ndarray
    done: jnp.ndarray
    success: jnp.ndarray
    invalid_action: jnp.ndarray
    unstable: jnp.ndarray


class _Env:
    """Episode length 2..13 steps from the reset key and task; success = the sum of the
    actions' first entries is positive; finished states are frozen, as TabletopEnv's."""

    def reset(self, key, task_id):
        length = 2 + jax.random.randint(key, (), 0, 9) + 3 * task_id
        f = jnp.zeros((), bool)
        return _State(step=jnp.zeros((), jnp.int32), length=length, total=jnp.zeros(()), done=f, success=f,
                      invalid_action=f, unstable=f)

    def step(self, state, action):
        step, total = state.step + 1, state.total + action[0]
        done = step >= state.length
        new = state.replace(step=step, total=total, done=done, success=done & (total > 0))
        return jax.tree.map(lambda old, n: jnp.where(state.done, old, n), state, new)


def _policy():
    def init(params, states):
        n = states.step.shape[0]
        return {"count": jnp.zeros(n, jnp.int32), "batch_calls": jnp.zeros((), jnp.int32)}

    def act(params, states, pstate, keys):
        a = jax.vmap(lambda k: jax.random.normal(k, (7,)))(keys) + 0.1 * pstate["count"][:, None]
        pstate = {"count": pstate["count"] + 1, "batch_calls": pstate["batch_calls"] + 1}
        return a, pstate, {"passes": jnp.ones(keys.shape[0]) * 7.0, "first": a[:, 0]}

    return rollout.Policy(name="stand-in", init=init, act=act)


N_EPISODES, N_QUEUE = 11, 12  # one padding row


@pytest.fixture(scope="module")
def case():
    keys = jax.random.split(jax.random.PRNGKey(3), N_QUEUE)
    task_ids = jnp.arange(N_QUEUE, dtype=jnp.int32) % 2
    final, totals, steps = jax.jit(lambda k, t: rollout.run_episodes(_Env(), _policy(), k, t, 100))(keys, task_ids)
    return keys, task_ids, final, totals, int(steps)


@pytest.mark.parametrize("slots,refills", [(3, 1), (3, 3), (4, None), (12, None)])
def test_every_episode_ends_as_when_run_alone(case, slots, refills):
    keys, task_ids, final, totals, _ = case
    run = jax.jit(lambda k, t, n: rollout.run_queue(_Env(), _policy(), k, t, n, slots, 1000,
                                                    refills_per_step=refills))
    out, loop_steps = run(keys, task_ids, jnp.int32(N_EPISODES))
    v = slice(0, N_EPISODES)
    np.testing.assert_array_equal(out.steps[v], final.step[v])
    np.testing.assert_array_equal(out.success[v], final.success[v])
    assert 0 < int(out.success[v].sum()) < N_EPISODES  # the outcomes depend on the actions
    for k in ("passes", "first"):
        np.testing.assert_allclose(out.totals[k][v], totals[k][v], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(out.totals["passes"][v], 7.0 * final.step[v])
    assert int(out.steps[N_EPISODES]) == 0  # the padding row never ran
    # the loop runs until the last episode ends; with one slot per episode, exactly as long as the batch
    assert int(loop_steps) >= int(final.step[v].max())
    if slots == N_QUEUE:
        assert int(loop_steps) == int(final.step[v].max())


def _sized_policy():
    """The stand-in policy, also reporting the batch size it acted at as a per-row stat."""
    base = _policy()

    def act(params, states, pstate, keys):
        a, pstate, stats = base.act(params, states, pstate, keys)
        return a, pstate, {**stats, "batch": jnp.full(keys.shape[0], keys.shape[0], jnp.float32)}

    return rollout.Policy(name="sized stand-in", init=base.init, act=act)


@pytest.mark.parametrize("slots,tail", [(4, 1), (4, 2), (3, 2)])
def test_a_tail_in_fewer_slots_ends_every_episode_as_when_run_alone(case, slots, tail):
    """Once the queue is empty and at most `tail` slots run, the loop goes on at that batch
    size: every episode ends as it does alone, in as many loop steps as without the tail,
    and the last episodes' final steps were taken at the smaller batch size."""
    keys, task_ids, final, totals, _ = case
    run = lambda tail_slots: jax.jit(lambda k, t, n: rollout.run_queue(  # noqa: E731
        _Env(), _sized_policy(), k, t, n, slots, 1000, tail_slots=tail_slots))(keys, task_ids, jnp.int32(N_EPISODES))
    (out, loop_steps), (full, full_steps) = run(tail), run(0)
    v = slice(0, N_EPISODES)
    np.testing.assert_array_equal(out.steps[v], final.step[v])
    np.testing.assert_array_equal(out.success[v], final.success[v])
    for k in ("passes", "first"):
        np.testing.assert_allclose(out.totals[k][v], totals[k][v], rtol=1e-6, atol=1e-6)
    assert int(loop_steps) == int(full_steps)
    np.testing.assert_array_equal(full.totals["batch"][v], slots * final.step[v])
    in_tail = np.asarray(out.totals["batch"][v]) < slots * np.asarray(final.step[v])
    assert 0 < in_tail.sum() <= tail  # only the episodes still running when the queue emptied
    assert np.all(np.asarray(out.totals["batch"][v]) >= tail * np.asarray(final.step[v]))


def test_a_tail_in_a_program_of_its_own_runs_as_in_one_program(case):
    """`run_queue(split=True)` then `run_queue_tail` on its carry, two programs (the evaluator
    compiles the second while the first runs), give what one program with the tail gives."""
    keys, task_ids, *_ = case
    n = jnp.int32(N_EPISODES)
    one = jax.jit(lambda k, t, n: rollout.run_queue(_Env(), _sized_policy(), k, t, n, 4, 1000, tail_slots=2))
    head = jax.jit(lambda k, t, n: rollout.run_queue(_Env(), _sized_policy(), k, t, n, 4, 1000, tail_slots=2,
                                                     split=True))
    tail = jax.jit(lambda c, n: rollout.run_queue_tail(_Env(), _sized_policy(), c, n, 1000, 2))
    (out, steps), (out2, steps2) = one(keys, task_ids, n), tail(head(keys, task_ids, n), n)
    assert int(steps) == int(steps2)
    jax.tree.map(np.testing.assert_array_equal, out, out2)


def test_starts_from_a_program_of_their_own_run_as_in_one_program(case):
    """The episodes' starts (`queue_starts`) compiled apart and handed to `run_queue` (as the
    evaluator compiles them beside the loop) give what one program gives, seed included."""
    keys, task_ids, *_ = case
    n = jnp.int32(N_EPISODES)
    one = jax.jit(lambda k, t, n: rollout.run_queue(_Env(), _policy(), k, t, n, 4, 1000, seed=5))
    starts = jax.jit(lambda k, t: rollout.queue_starts(_Env(), k, t, seed=5))
    loop = jax.jit(lambda st, n: rollout.run_queue(_Env(), _policy(), None, None, n, 4, 1000, starts=st))
    (out, steps), (out2, steps2) = one(keys, task_ids, n), loop(starts(keys, task_ids), n)
    assert int(steps) == int(steps2)
    jax.tree.map(np.testing.assert_array_equal, out, out2)
    text = str(jax.make_jaxpr(lambda st, n: rollout.run_queue(_MarkedEnv(), _policy(), None, None, n, 4, 100,
                                                              starts=st))(starts(keys, task_ids), n))
    assert "population_count" not in text  # the loop's program holds no env reset


def test_a_tail_not_below_the_slots_is_refused(case):
    keys, task_ids, *_ = case
    for tail in (-1, 4, 5):
        with pytest.raises(ValueError, match="tail_slots must be 0"):
            rollout.run_queue(_Env(), _policy(), keys, task_ids, jnp.int32(N_EPISODES), 4, 100, tail_slots=tail)


def test_fewer_slots_run_fewer_env_steps_than_batches_waiting_for_their_slowest(case):
    keys, task_ids, final, _, _ = case
    slots = 4
    out, loop_steps = jax.jit(lambda k, t, n: rollout.run_queue(_Env(), _policy(), k, t, n, slots, 1000))(
        keys, task_ids, jnp.int32(N_QUEUE))
    lengths = np.asarray(final.step)
    batched = sum(lengths[i: i + slots].max() for i in range(0, N_QUEUE, slots))  # control steps, 3 batches
    assert int(loop_steps) < batched
    assert int(loop_steps) >= -(-lengths.sum() // slots)  # no slot runs two episodes at once


def test_the_loop_bound_stops_the_queue(case):
    keys, task_ids, _, _, _ = case
    out, loop_steps = jax.jit(lambda k, t, n: rollout.run_queue(_Env(), _policy(), k, t, n, 2, 5))(
        keys, task_ids, jnp.int32(N_EPISODES))
    assert int(loop_steps) == 5
    assert int((out.steps > 0).sum()) < N_EPISODES


class _MarkedEnv(_Env):
    """The stand-in env with a primitive (population_count) that only its reset uses, to
    count the resets a traced program holds."""

    def reset(self, key, task_id):
        state = super().reset(key, task_id)
        return state.replace(length=state.length + 0 * jax.lax.population_count(task_id))


def test_the_program_holds_one_env_reset(case):
    """The first fill and every refill take their states from one reset of the whole queue
    (the env reset is a large share of the compile), for a batch of slots as for one."""
    keys, task_ids, *_ = case
    for slots in (1, 4, 12):
        text = str(jax.make_jaxpr(lambda k, t, n: rollout.run_queue(_MarkedEnv(), _policy(), k, t, n, slots, 100))(
            keys, task_ids, jnp.int32(N_EPISODES)))
        assert text.count("population_count") == 1, slots


class _StagedEnv(_Env):
    """The stand-in env with its step in three stages, as TabletopEnv.step_stages splits its own."""

    @property
    def step_stages(self):
        return (lambda st, a: a[0] * 2.0,
                lambda st, x: (x, st.step + 1),
                lambda st, x: _Env.step(self, st, jnp.full((7,), x[0] / 2.0)))


def _driven(env, slots, n, tail_slots=0, refills=None):
    """`queue_loop`'s functions, each jitted apart, driven from the host (as the evaluator runs them)."""
    loop = rollout.queue_loop(env, _sized_policy(), slots, 1000, refills_per_step=refills, tail_slots=tail_slots)
    loop = rollout.QueueLoop(jax.jit(loop.first), tuple(map(jax.jit, loop.stages)), jax.jit(loop.turn))
    return lambda starts: rollout.drive_queue(loop, None, starts, n)


@pytest.mark.parametrize("env", [_Env(), _StagedEnv()], ids=["one stage", "three stages"])
@pytest.mark.parametrize("slots,refills", [(3, 1), (4, None), (12, None)])
def test_a_host_driven_loop_of_programs_runs_as_one_program(case, env, slots, refills):
    """`queue_loop`'s programs driven from the host (`drive_queue`, `alive` read a round late)
    end every episode, and the loop, exactly as `run_queue`'s one program."""
    keys, task_ids, *_ = case
    n = jnp.int32(N_EPISODES)
    starts = jax.jit(lambda k, t: rollout.queue_starts(_Env(), k, t))(keys, task_ids)
    one = jax.jit(lambda st, n: rollout.run_queue(_Env(), _sized_policy(), None, None, n, slots, 1000,
                                                  refills_per_step=refills, starts=st))
    out, steps = one(starts, n)
    c = _driven(env, slots, n, refills=refills)(starts)
    assert int(steps) == int(c[0])
    jax.tree.map(np.testing.assert_array_equal, out, c[-1])


def test_a_round_past_the_end_changes_nothing(case):
    """A round run after `alive` turned False (the host reads it a round late) leaves the
    carry as it was, at the queue's end as at the loop bound with episodes still running."""
    keys, task_ids, *_ = case
    starts = jax.jit(lambda k, t: rollout.queue_starts(_Env(), k, t))(keys, task_ids)
    n = jnp.int32(N_EPISODES)
    for bound in (1000, 6):
        loop = rollout.queue_loop(_StagedEnv(), _sized_policy(), 4, bound)
        first, middle, turn = jax.jit(loop.first), jax.jit(loop.stages[0]), jax.jit(loop.turn)
        c, x, go = first(None, starts, n)
        alive = True
        while alive:
            c, x, go, alive = turn(None, c, middle(rollout.queue_states(c), x), go, starts, n)
        c2, *_ = turn(None, c, middle(rollout.queue_states(c), x), go, starts, n)
        assert not bool(go)
        jax.tree.map(np.testing.assert_array_equal, c, c2)
        assert (int(c[0]) == 6) == (bound == 6) and (int(jnp.sum(c[-1].steps > 0)) < N_EPISODES) == (bound == 6)


def test_a_host_driven_loop_stops_where_the_tail_starts(case):
    """With `tail_slots`, the driven loop's carry is the one-program head's, which
    `run_queue_tail`, or a driven loop of the tail's slots, finishes as one program with the
    tail does."""
    keys, task_ids, *_ = case
    n = jnp.int32(N_EPISODES)
    starts = jax.jit(lambda k, t: rollout.queue_starts(_Env(), k, t))(keys, task_ids)
    one = jax.jit(lambda st, n: rollout.run_queue(_Env(), _sized_policy(), None, None, n, 4, 1000, tail_slots=2,
                                                  starts=st))
    tail = jax.jit(lambda c, n: rollout.run_queue_tail(_Env(), _sized_policy(), c, n, 1000, 2))
    head = _driven(_StagedEnv(), 4, n, tail_slots=2)(starts)
    (out, steps), (out2, steps2) = one(starts, n), tail(head, n)
    assert int(steps) == int(steps2)
    jax.tree.map(np.testing.assert_array_equal, out, out2)
    # the tail as programs driven from the host too: a queue loop of 2 slots from the head's carry
    loop = rollout.queue_loop(_StagedEnv(), _sized_policy(), 2, 1000)
    loop = rollout.QueueLoop(jax.jit(loop.first), tuple(map(jax.jit, loop.stages)), jax.jit(loop.turn))
    c = rollout.drive_queue(loop, None, starts, n, carry=head)
    assert int(c[0]) == int(steps)
    jax.tree.map(np.testing.assert_array_equal, out, c[-1])


def test_episodes_ended_mid_queue_hold_their_final_results(case):
    """Read every round as the evaluator reads it to save progress: an episode counted as
    ended stays so, its results row is already the final one, and by the end every valid
    episode has ended; through a tail's loop too."""
    keys, task_ids, *_ = case
    n = jnp.int32(N_EPISODES)
    starts = jax.jit(lambda k, t: rollout.queue_starts(_Env(), k, t))(keys, task_ids)
    seen = []

    def each_round(c):
        next_ep, slot_ep, results = jax.device_get((c[2], c[3], c[-1]))
        seen.append((rollout.ended_episodes(next_ep, slot_ep, N_QUEUE), results))

    head_loop = rollout.queue_loop(_StagedEnv(), _sized_policy(), 4, 1000, tail_slots=2)
    tail_loop = rollout.queue_loop(_StagedEnv(), _sized_policy(), 2, 1000)
    jitted = [rollout.QueueLoop(jax.jit(lp.first), tuple(map(jax.jit, lp.stages)), jax.jit(lp.turn))
              for lp in (head_loop, tail_loop)]
    head = rollout.drive_queue(jitted[0], None, starts, n, each_round=each_round)
    rounds_in_head = len(seen)
    final = rollout.drive_queue(jitted[1], None, starts, n, carry=head, each_round=each_round)[-1]
    assert 0 < rounds_in_head < len(seen)
    masks = np.stack([m for m, _ in seen])
    assert masks[0].sum() < N_EPISODES <= masks[-1].sum() and not masks[-1][N_EPISODES:].any()
    assert np.all(masks[1:] >= masks[:-1])  # once ended, always ended
    assert 0 < masks[rounds_in_head - 1].sum() < N_EPISODES  # the head saves some before the tail
    for ended, results in seen:
        jax.tree.map(lambda r, f: np.testing.assert_array_equal(np.asarray(r)[ended], np.asarray(f)[ended]),
                     results, final)
