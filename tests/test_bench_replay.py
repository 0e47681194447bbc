"""The decode benchmark (experiments.bench_methods) replays only running steps: lanes of episodes back to back,
each lane cut to the shortest, and a policy's per-row state reset where an episode starts."""

import jax.numpy as jnp
import numpy as np
import pytest

from envs import rollout


def _running(lengths, steps):
    return np.arange(steps)[:, None] < np.asarray(lengths)[None, :]


def test_lanes_play_episodes_back_to_back_and_only_running_steps():
    running = _running([3, 5, 2, 4], steps=6)
    t, e = rollout.replay_lanes(running, envs=4, batch=2)
    # lane 0: env 0 (3 steps) then env 2 (2): 5; lane 1: env 1 (5) then env 3 (4): 9; cut to 5.
    assert t.shape == e.shape == (5, 2)
    assert e[:, 0].tolist() == [0, 0, 0, 2, 2] and t[:, 0].tolist() == [0, 1, 2, 0, 1]
    assert e[:, 1].tolist() == [1] * 5 and t[:, 1].tolist() == [0, 1, 2, 3, 4]
    assert running[t, e].all()
    t1, e1 = rollout.replay_lanes(running, envs=3, batch=1)  # batch 1: the first `envs` envs in turn
    assert e1[:, 0].tolist() == [0] * 3 + [1] * 5 + [2] * 2


def test_lanes_refuse_a_recording_they_cannot_replay():
    with pytest.raises(ValueError, match="runs again after its episode ended"):
        rollout.replay_lanes(np.asarray([[True], [False], [True]]), envs=1, batch=1)
    with pytest.raises(ValueError, match="a lane of batch 2 has no running step"):
        rollout.replay_lanes(_running([3, 0], steps=4), envs=2, batch=2)


def _policy_with_a_batch_wide_leaf(options=6):
    """A policy state as HeiSD's: per-env rows, and one entry per draft option for the batch."""
    def init(params, states):
        return {"rows": jnp.zeros((states.shape[0], 2)), "shared": jnp.ones((options,))}
    return rollout.Policy(name="fake", init=init, act=None)


def test_per_row_leaves_tell_a_batch_wide_leaf_from_a_per_env_one_of_the_same_length():
    policy = _policy_with_a_batch_wide_leaf(options=6)
    assert rollout.per_row_leaves(policy, jnp.zeros((6, 3))) == {"rows": True, "shared": False}


def test_rows_set_resets_only_the_rows_given_and_keeps_batch_wide_leaves():
    policy = _policy_with_a_batch_wide_leaf(options=3)  # as long as the batch: shape alone cannot tell
    per_row = rollout.per_row_leaves(policy, jnp.zeros((3, 1)))
    old = {"rows": jnp.arange(6.0).reshape(3, 2), "shared": jnp.ones((3,))}
    new = {"rows": -jnp.ones((3, 2)), "shared": jnp.zeros((3,))}
    out = rollout.rows_set(jnp.asarray([3, 1, 3]), new, old, per_row)  # row 1; index 3: none
    assert out["rows"].tolist() == [[0, 1], [-1, -1], [4, 5]]
    assert out["shared"].tolist() == [1.0] * 3
    assert rollout.rows_set(jnp.asarray([3, 1, 3]), new, old, per_row, shared_too=True)["shared"].tolist() == [0.0] * 3
