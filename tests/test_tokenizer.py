"""Action tokenizer: round trips within half a bin, monotone ids in the vocabulary's tail."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax.tokenizer import N_BINS, ActionTokenizer


@pytest.fixture(scope="module")
def tok():
    rng = np.random.default_rng(0)
    actions = np.concatenate([rng.uniform(-0.8, 0.9, (2000, 6)), rng.choice([-1.0, 1.0], (2000, 1))], -1)
    return ActionTokenizer.fit(actions, vocab_size=300), actions


def test_round_trip_within_half_a_bin(tok):
    t, actions = tok
    inside = actions[np.all((actions >= np.array(t.q01)) & (actions <= np.array(t.q99)), -1)]
    back = np.asarray(jax.jit(lambda a: t.to_actions(t.to_ids(a)))(inside))
    half_bin = (np.array(t.q99) - np.array(t.q01)) / N_BINS / 2
    assert np.all(np.abs(back - inside) <= half_bin + 1e-6)


def test_ids_are_the_last_bins_and_monotone(tok):
    t, _ = tok
    lo, hi = np.array(t.q01), np.array(t.q99)
    ids = np.asarray(t.to_ids(jnp.asarray(np.stack([lo - 1, hi + 1]))))
    np.testing.assert_array_equal(ids[0], np.full(7, t.vocab_size - N_BINS))
    np.testing.assert_array_equal(ids[1], np.full(7, t.vocab_size - 1))
    sweep = np.linspace(lo, hi, 50)
    assert np.all(np.diff(np.asarray(t.to_ids(jnp.asarray(sweep))), axis=0) >= 0)


def test_gripper_is_not_renormalised(tok):
    t, _ = tok
    assert t.q01[6] == -1.0 and t.q99[6] == 1.0
    np.testing.assert_allclose(np.asarray(t.to_actions(t.to_ids(jnp.array([0, 0, 0, 0, 0, 0, 1.0]))))[6], 1 - 1 / N_BINS)


def test_dict_round_trip_and_bad_statistics(tok):
    t, _ = tok
    assert ActionTokenizer.from_dict(t.to_dict()) == t
    with pytest.raises(ValueError, match="q99 must exceed q01"):
        ActionTokenizer((0.0,) * 7, (0.0,) * 7, 300)
    with pytest.raises(ValueError, match="vocab_size"):
        ActionTokenizer((-1.0,) * 7, (1.0,) * 7, 100)
