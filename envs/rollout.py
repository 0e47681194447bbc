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
from typing import Any, Callable

import jax
import jax.numpy as jnp

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


def _start(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray, seed: int = 0):
    reset_keys, act_keys = jax.vmap(lambda k: jax.random.split(k))(keys).transpose(1, 0, 2)
    if seed:  # a Python int: seed 0 keeps the historical keys
        act_keys = jax.vmap(lambda k: jax.random.fold_in(k, seed))(act_keys)
    state = jax.vmap(env.reset)(reset_keys, task_ids)
    return state, policy.init(policy.params, state), act_keys


def _act(policy: Policy, state, pstate, act_keys, t):
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


def record_episodes(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray, n_steps: int,
                    exec_noise: float = 0.0, teacher: Policy | None = None, beta: float = 0.0):
    """Like run_episodes for exactly `n_steps`, also returning the trajectory: a dict of
    [n_steps, B, ...] arrays (observation before each action, the action, ee kinematics,
    done, and the policy's per-step decode statistics under "stats").

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

    (state, _, _), traj = jax.lax.scan(body, (state, pstate, tstate), jnp.arange(n_steps))
    return state, traj
