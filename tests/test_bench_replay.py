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


def test_env_interval_resamples_whole_episodes():
    """A figure over replayed episodes moves with the episodes drawn: x AR's 5-95 % range over
    envs resampled with replacement. Alike episodes give no range at all; episodes at 4x and 2x
    AR give a range inside [2x, 4x] around the pooled 2.67x, and more draws of the same
    episodes narrow it; steps are weighted as they count, not episodes."""
    from heisd_jax.harness import replay
    env = np.repeat(np.arange(10), 20)
    assert replay.env_interval(np.full(200, 10.0), 40.0, env) == pytest.approx([4.0, 4.0])
    ms = np.where(env < 5, 10.0, 20.0)
    lo, hi = replay.env_interval(ms, 40.0, env)
    assert 2.0 < lo < 40.0 * 200 / ms.sum() < hi < 4.0
    many = np.repeat(np.arange(200), 20)
    lo2, hi2 = replay.env_interval(np.where(many < 100, 10.0, 20.0), 40.0, many)
    assert lo < lo2 < hi2 < hi
    # one long slow episode (2x) among four short fast ones (4x): drawn, its steps pull the
    # figure to ~2x (a mean over episodes would stay near 3.6x); left out (a third of draws), 4x
    env3 = np.concatenate([np.zeros(100, int), np.repeat(np.arange(1, 5), 5)])
    lo3, hi3 = replay.env_interval(np.where(env3 == 0, 20.0, 10.0), 40.0, env3)
    assert 2.0 < lo3 < 2.2 and hi3 == pytest.approx(4.0)
