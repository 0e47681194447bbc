"""The retrieval datastore: kNN against brute force, task isolation, save/load and refusals."""

import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import retrieval
from heisd_jax.harness.offline import datastore
from heisd_jax.tokenizer import ActionTokenizer

TOK = ActionTokenizer((-1.0,) * 7, (1.0,) * 7, 300)
SPEC = retrieval.KeySpec(history=2)


def _episodes(rng, n=6, t=25):
    for i in range(n):
        yield i % 3, rng.uniform(-1, 1, (t, 7)).astype(np.float32), rng.normal(size=(t, 8)).astype(np.float32)


@pytest.fixture(scope="module")
def store():
    return datastore.build(SPEC, TOK, _episodes(np.random.default_rng(0)))


def test_episode_history_is_the_previous_actions_zero_padded():
    a = np.arange(4 * 7, dtype=np.float32).reshape(4, 7)
    h = datastore.episode_history(a, 2)
    np.testing.assert_array_equal(h[0], 0)
    np.testing.assert_array_equal(h[1], np.stack([np.zeros(7), a[0]]))
    np.testing.assert_array_equal(h[3], a[1:3])


def test_knn_equals_brute_force_within_the_task(store):
    rng = np.random.default_rng(1)
    q = rng.normal(size=(5, SPEC.dim)).astype(np.float32)
    task = np.array([0, 1, 2, 0, 1])
    tokens, dist, valid = retrieval.query(store, jnp.asarray(q), jnp.asarray(task), 4)
    keys, toks, tasks = map(np.asarray, (store.keys, store.tokens, store.task))
    for b in range(5):
        d = ((keys - q[b]) ** 2).sum(-1)
        d[tasks != task[b]] = np.inf
        order = np.argsort(d)[:4]
        np.testing.assert_allclose(np.asarray(dist[b]), d[order], rtol=1e-4, atol=1e-3)
        np.testing.assert_array_equal(np.asarray(tokens[b]), toks[order])
        assert bool(valid[b].all())


def test_queries_never_match_other_tasks_and_invalid_slots_are_masked(store):
    q = jnp.zeros((1, SPEC.dim))
    n_task0 = int((np.asarray(store.task) == 0).sum())
    _, dist, valid = retrieval.query(store, q, jnp.array([0]), n_task0 + 3)
    assert int(valid.sum()) == n_task0 and not bool(valid[0, -1])
    _, _, valid = retrieval.query(store, q, jnp.array([7]), 4)  # a task with no entries
    assert not bool(valid.any())
    _, _, near = retrieval.query(store, q, jnp.array([0]), 4, max_dist=0.0)
    assert not bool(near.any())


def test_save_load_round_trip_and_refusals(store, tmp_path):
    path = tmp_path / "ds"
    datastore.save(path, store, SPEC, TOK, "abc")
    loaded, spec, meta = retrieval.load(path, TOK, "abc")
    assert spec == SPEC and meta["size"] == store.size
    np.testing.assert_array_equal(np.asarray(loaded.tokens), np.asarray(store.tokens))
    np.testing.assert_allclose(np.asarray(loaded.keys), np.asarray(store.keys), rtol=1e-3, atol=1e-3)  # float16
    with pytest.raises(ValueError, match="another target"):
        retrieval.load(path, TOK, "xyz")
    with pytest.raises(ValueError, match="another action tokenizer"):
        retrieval.load(path, ActionTokenizer((-2.0,) * 7, (2.0,) * 7, 300), "abc")
    (path / "datastore.npz").write_bytes((path / "datastore.npz").read_bytes()[:100])
    with pytest.raises(ValueError, match="cannot read"):
        retrieval.load(path, TOK, "abc")
    with pytest.raises(ValueError, match="no readable datastore"):
        retrieval.load(tmp_path / "none", TOK, "abc")


def test_build_from_demos_keys_each_step_by_its_history(tmp_path):
    from envs import demos, tasks as tasks_lib

    rng = np.random.default_rng(2)
    n = 6
    w = demos.DatasetWriter(tmp_path / "d", {"image_size": 4})
    steps = dict(image=np.zeros((2 * n, 4, 4, 3), np.uint8), proprio=rng.normal(size=(2 * n, 8)).astype(np.float32),
                 action=rng.uniform(-1, 1, (2 * n, 7)).astype(np.float32), ee_vel=np.zeros((2 * n, 3), np.float32),
                 ee_ang_vel=np.zeros((2 * n, 3), np.float32), ee_acc=np.zeros((2 * n, 3), np.float32),
                 gripper_vel=np.zeros(2 * n, np.float32))
    w.add_shard(steps, [dict(task="lift_blue_cylinder", instruction="x", start=i * n, length=n) for i in range(2)])
    store = datastore.build_from_demos(w.finalize(), SPEC, TOK)
    assert store.size == 2 * n
    assert set(np.asarray(store.task).tolist()) == {[t.name for t in tasks_lib.ALL_TASKS].index("lift_blue_cylinder")}
    keys = np.asarray(store.keys)
    np.testing.assert_array_equal(keys[n, :14], 0)  # first step of the second episode: no history
    np.testing.assert_allclose(keys[n + 2, :14], steps["action"][n:n + 2].reshape(-1), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(store.tokens), np.asarray(TOK.to_ids(jnp.asarray(steps["action"]))))
    # Episodes a policy drove: what it executed (here bin centres, as a detokenized action is)
    # replaces the recorded labels in the keys' histories and in the values.
    executed = np.asarray(TOK.to_actions(TOK.to_ids(jnp.asarray(-steps["action"]))), np.float32)
    driven = datastore.build_from_demos(tmp_path / "d", SPEC, TOK, actions=executed)
    np.testing.assert_allclose(np.asarray(driven.keys)[n + 2, :14], np.clip(executed[n:n + 2], -1, 1).reshape(-1),
                               rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(driven.tokens), np.asarray(TOK.to_ids(jnp.asarray(-steps["action"]))))
    np.testing.assert_array_equal(np.asarray(driven.keys)[:, 14:], keys[:, 14:])  # proprio unchanged
    with pytest.raises(ValueError, match="11 actions given for 12 steps"):
        datastore.build_from_demos(tmp_path / "d", SPEC, TOK, actions=executed[:-1])


def test_holdout_split_is_disjoint_and_covers_every_episode():
    keep, held = datastore.strided_episode_split(25, 0.1)
    assert sorted(keep + held) == list(range(25)) and not set(keep) & set(held) and held == [9, 19]
    assert datastore.strided_episode_split(5, 0.0) == ([0, 1, 2, 3, 4], [])
    with pytest.raises(ValueError, match="holdout"):
        datastore.strided_episode_split(5, 1.0)


def test_with_values_replaces_the_values_and_refuses_a_mismatch(store):
    new = np.asarray(store.tokens)[:, ::-1].copy()
    np.testing.assert_array_equal(np.asarray(datastore.with_values(store, new).tokens), new)
    with pytest.raises(ValueError, match="do not match"):
        datastore.with_values(store, new[1:])
