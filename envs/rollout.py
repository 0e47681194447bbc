"""Policy-in-the-loop rollouts: one jitted function, control steps under a loop, envs vmapped.

A policy is a pair of pure per-env functions, `init(env_state) -> policy_state` and
`act(env_state, policy_state, key) -> (action [7], policy_state)`; the rollout vmaps them
with the environment. Finished envs are frozen by the environment itself.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp

from envs.env import EnvState, TabletopEnv


@dataclasses.dataclass(frozen=True)
class Policy:
    name: str
    init: Callable[[EnvState], Any]
    act: Callable[[EnvState, Any, jax.Array], tuple[jnp.ndarray, Any]]


def _start(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray):
    reset_keys, act_keys = jax.vmap(lambda k: jax.random.split(k))(keys).transpose(1, 0, 2)
    state = jax.vmap(env.reset)(reset_keys, task_ids)
    return state, jax.vmap(policy.init)(state), act_keys


def _act(policy: Policy, state, pstate, act_keys, t):
    k = jax.vmap(lambda k: jax.random.fold_in(k, t))(act_keys)
    return jax.vmap(policy.act)(state, pstate, k)


def run_episodes(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray, max_steps: int) -> EnvState:
    """Runs a batch of episodes to the end (all done, or `max_steps`); returns final states.
    `keys` [B, 2] are initial-state keys (see TabletopEnv.initial_state_keys)."""
    state, pstate, act_keys = _start(env, policy, keys, task_ids)

    def cond(c):
        t, state, _ = c
        return (t < max_steps) & ~jnp.all(state.done)

    def body(c):
        t, state, pstate = c
        action, pstate = _act(policy, state, pstate, act_keys, t)
        return t + 1, jax.vmap(env.step)(state, action), pstate

    _, state, _ = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), state, pstate))
    return state


def record_episodes(env: TabletopEnv, policy: Policy, keys: jax.Array, task_ids: jnp.ndarray, n_steps: int,
                    exec_noise: float = 0.0):
    """Like run_episodes for exactly `n_steps`, also returning the trajectory: a dict of
    [n_steps, B, ...] arrays (observation before each action, the action, ee kinematics).

    exec_noise: std of Gaussian noise added to the six motion dimensions of the *executed*
    action only; the recorded action is the policy's own (noise injection as in DART: more
    diverse states, clean labels)."""
    state, pstate, act_keys = _start(env, policy, keys, task_ids)

    def body(carry, t):
        state, pstate = carry
        action, pstate = _act(policy, state, pstate, act_keys, t)
        out = dict(image=state.obs.image, proprio=state.obs.proprio, action=action, ee_vel=state.kin.lin_vel,
                   ee_ang_vel=state.kin.ang_vel, ee_acc=state.kin.lin_acc, gripper_vel=state.kin.gripper_vel)
        noise_keys = jax.vmap(lambda k: jax.random.fold_in(jax.random.fold_in(k, t), 1))(act_keys)
        noise = exec_noise * jax.vmap(lambda k: jax.random.normal(k, (6,)))(noise_keys)
        executed = action.at[:, :6].set(jnp.clip(action[:, :6] + noise, -1.0, 1.0))
        return (jax.vmap(env.step)(state, executed), pstate), out

    (state, _), traj = jax.lax.scan(body, (state, pstate), jnp.arange(n_steps))
    return state, traj
