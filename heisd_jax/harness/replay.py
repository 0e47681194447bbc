"""Closed-loop steps recorded once, for replaying decoders on them open loop
(experiments.bench_methods times every method on the same inputs; studies.action_repeats
measures how actions repeat).

`record` rolls a policy out from the fixed evaluation initial states and keeps, per control
step and env, what a decoding policy reads (`ReplayState`: observation, end-effector
kinematics, task, step), the action taken and whether the episode had ended; `replay_fn`
plays a policy over such states, open loop; `env_interval` says how far a figure over a few
replayed episodes moves with the episodes drawn.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import rollout
from envs.env import TabletopEnv
from heisd_jax.observation import Observation


@struct.dataclass
class ReplayKinematics:
    lin_vel: jnp.ndarray
    ang_vel: jnp.ndarray
    lin_acc: jnp.ndarray
    gripper_vel: jnp.ndarray


@struct.dataclass
class ReplayInfo:
    task_id: jnp.ndarray


@struct.dataclass
class ReplayState:
    """The fields of `envs.env.EnvState` that decoding policies read."""
    obs: Observation
    kin: ReplayKinematics
    info: ReplayInfo
    step: jnp.ndarray


def record(env: TabletopEnv, policy: rollout.Policy, n_envs: int, n_steps: int):
    """`policy` run for n_steps control steps in n_envs envs (the evaluation initial states,
    cycling over the tasks): replay states [T, B], the actions taken [T, B, 7] and the
    done flags [T, B]."""
    tids, keys = env.cycling_eval_starts(n_envs)
    fn = jax.jit(lambda p, k, t: rollout.record_episodes(env, dataclasses.replace(policy, params=p), k, t, n_steps))
    final, traj = fn(policy.params, keys, jnp.asarray(tids, jnp.int32))
    t = n_steps
    states = ReplayState(
        obs=Observation(image=traj["image"], proprio=traj["proprio"],
                        instruction=jnp.broadcast_to(final.obs.instruction, (t,) + final.obs.instruction.shape)),
        kin=ReplayKinematics(lin_vel=traj["ee_vel"], ang_vel=traj["ee_ang_vel"], lin_acc=traj["ee_acc"],
                             gripper_vel=traj["gripper_vel"]),
        info=ReplayInfo(task_id=jnp.broadcast_to(jnp.asarray(tids, jnp.int32), (t, n_envs))),
        step=jnp.broadcast_to(jnp.arange(t)[:, None], (t, n_envs)))
    return states, traj["action"], traj["done"]


def replay_fn(policy: rollout.Policy, compiler_options=None):
    """A jitted (params, states [T, B]) -> (actions [T, B, 7], stats per step): `policy` acting
    on each recorded step in turn, its own state carried from step to step and started afresh
    in the rows whose episode starts there."""
    def run(params, states):
        first = jax.tree.map(lambda x: x[0], states)
        pstate = policy.init(params, first)
        b = first.step.shape[0]
        keys = jnp.zeros((b, 2), jnp.uint32)
        per_row = rollout.per_row_leaves(policy, first)

        def body(pstate, s):
            fresh = policy.init(params, s)  # rows whose episode starts here begin from a fresh state
            pstate = rollout.rows_set(jnp.where(s.step == 0, jnp.arange(b), b), fresh, pstate, per_row)
            actions, pstate, stats = policy.act(params, s, pstate, keys)
            return pstate, (actions, stats)
        return jax.lax.scan(body, pstate, states)[1]
    return jax.jit(run, compiler_options=compiler_options)


def env_interval(ms: np.ndarray, ar_ms: float, env: np.ndarray, draws: int = 2000, seed: int = 0) -> list[float]:
    """The 5th and 95th percentiles of x AR over the replayed envs resampled with replacement
    (whole episodes, the unit a replay samples): how far a figure over this many envs moves
    with the envs drawn. ms: priced ms per step; env: each step's recorded env."""
    ids, which = np.unique(env, return_inverse=True)
    spent = np.bincount(which, ms, len(ids))
    steps = np.bincount(which, minlength=len(ids))
    pick = np.random.default_rng(seed).integers(0, len(ids), (draws, len(ids)))
    ratio = ar_ms * steps[pick].sum(1) / spent[pick].sum(1)
    return np.percentile(ratio, [5, 95]).tolist()
