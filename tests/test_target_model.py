"""The target-model interface: a second target plugs into every decoder by implementing it.

`HistoryTarget` below is that second target, written against the interface alone: it keeps
no keys or values at all. Its "cache" is the observation and the committed token ids, and
every pass recomputes the prompt, the history and the new block in one forward pass
(`vla.prefill_with_block` with the history as a causal chain ahead of the block). It shares
the shipped VLA's weights, so every decoder must give the same tokens with it as with
`VLATarget`: greedy AR, strict speculative decoding (lossless) and the HeiSD decode.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import acceptance, hybrid, spec_decode as sd, target_model, vla
from heisd_jax.observation import Observation

from tiny_models import CFG, HYBRID_B, aligned_pair, candidates, obs as make_obs


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class History:
    obs: Observation
    tokens: jnp.ndarray  # [B, K] committed token ids (valid: j < n)
    n: jnp.ndarray  # [B]


@dataclasses.dataclass(frozen=True)
class HistoryTarget:
    """The VLA without a KV cache: each pass recomputes everything it attends to."""

    cfg: vla.VLAConfig
    slots: int = 16  # committed tokens one action can need (7 + a tree's depth)

    def _empty(self, obs):
        b = obs.proprio.shape[0]
        return History(obs=obs, tokens=jnp.zeros((b, self.slots), jnp.int32), n=jnp.zeros((b,), jnp.int32))

    def prefill(self, params, obs):
        logits, hidden, x, _ = vla.prefill_features(params, self.cfg, obs)
        return logits, hidden, x, self._empty(obs)

    def prefill_with_block(self, params, obs, tokens, depth, intra):
        logits, hidden, x, blogits, bhidden, _, _ = vla.prefill_with_block(params, self.cfg, obs, tokens, depth, intra)
        return logits, hidden, x, blogits, bhidden, self._empty(obs), tokens

    def cached_pass(self, params, cache: History, tokens, depth, intra):
        b, t = tokens.shape
        k = self.slots
        valid = jnp.arange(k)[None] < cache.n[:, None]  # [B, K]
        chain = jnp.tril(jnp.ones((k, k), bool))[None] & valid[:, None, :]
        mask = jnp.concatenate([jnp.concatenate([chain, jnp.zeros((b, k, t), bool)], 2),
                                jnp.concatenate([jnp.broadcast_to(valid[:, None, :], (b, t, k)), intra], 2)], 1)
        offsets = jnp.concatenate([jnp.broadcast_to(jnp.arange(k), (b, k)), cache.n[:, None] + depth], 1)
        _, _, _, blogits, bhidden, _, _ = vla.prefill_with_block(
            params, self.cfg, cache.obs, jnp.concatenate([cache.tokens, tokens], 1), offsets, mask)
        return blogits[:, k:], bhidden[:, k:], tokens

    def commit(self, cache: History, block, src, n):
        b, kk = src.shape
        j = jnp.arange(kk)[None]
        dst = jnp.where(j < n[:, None], cache.n[:, None] + j, self.slots)  # out of range: dropped
        kept = jnp.take_along_axis(block, src, 1)
        tokens = cache.tokens.at[jnp.arange(b)[:, None], dst].set(kept, mode="drop")
        return History(obs=cache.obs, tokens=tokens, n=cache.n + n)

    def select_cache(self, rows, new, old):
        return target_model.select_rows(rows, new, old)

    def embed_tokens(self, params, tokens):
        return vla.embed_tokens(params, tokens)

    def action_head(self, params, hidden):
        return vla.action_head(params, self.cfg, hidden)


SECOND = HistoryTarget(CFG)


@pytest.fixture(scope="module")
def models():
    tp, dp = aligned_pair(0.35)  # partial acceptance: several rounds, rows of different lengths
    obs = make_obs(1, batch=HYBRID_B)
    ar = jax.jit(lambda p, o: target_model.ar_decode(p, CFG, o)[0])(tp, obs)
    return {"target": tp, "drafter": dp}, obs, np.asarray(ar)


def test_ar_with_the_second_target_equals_the_shipped_one(models):
    params, obs, ar = models
    tokens, passes = jax.jit(target_model.ar_decode, static_argnums=1)(params["target"], SECOND, obs)
    np.testing.assert_array_equal(np.asarray(tokens), ar)
    assert passes == 7


def test_strict_speculative_decoding_with_the_second_target_equals_ar(models):
    params, obs, ar = models
    spec = sd.SpecConfig(top_k=4, depth=4, total_tokens=16)
    tokens, stats = sd.decode_action(params, SECOND, obs, spec)
    np.testing.assert_array_equal(np.asarray(tokens), ar)
    mine = np.asarray(stats["target_passes"])
    _, ref = sd.decode_action(params, CFG, obs, spec)  # the same drafts: the same passes
    np.testing.assert_array_equal(mine, np.asarray(ref["target_passes"]))
    assert mine.min() < 7


@pytest.mark.parametrize("verify,continuation", [("prefill", "drafter"), ("separate", "ar")])
def test_strict_heisd_decode_with_the_second_target_equals_ar(models, verify, continuation):
    params, obs, ar = models
    cand, cuts = candidates(ar, np.random.default_rng(2))
    hcfg = dataclasses.replace(hybrid.PAPER, spec=sd.SpecConfig(top_k=2, depth=2, total_tokens=4), mode="retrieval",
                               acceptance="strict", n_candidates=3, skip=acceptance.SkipConfig(enabled=False),
                               verify=verify, continuation=continuation)
    use, valid, skip = jnp.ones((HYBRID_B,), bool), jnp.ones((HYBRID_B, 3), bool), jnp.zeros((HYBRID_B,), bool)
    decode = jax.jit(hybrid.decode, static_argnums=(1, 2))
    tokens, stats = decode(params, SECOND, hcfg, obs, cand, valid, use, skip)
    np.testing.assert_array_equal(np.asarray(tokens), ar)
    assert np.all(np.asarray(stats["retrieval_accepted"]) >= cuts)


def test_a_model_that_is_not_a_target_is_refused_by_name():
    with pytest.raises(TypeError, match=r"missing \['prefill_with_block'"):
        target_model.as_target(type("Half", (), {"cfg": CFG, "prefill": None})())
    assert target_model.as_target(CFG) == target_model.VLATarget(CFG)
