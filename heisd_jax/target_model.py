"""The target-model interface every decoder talks to, and greedy AR decoding written over it.

A decoder (`spec_decode`, `hybrid`, `cost_model`) never calls a model's functions or reads
its cache: it holds a `TargetModel` and calls these members only.

  prefill(params, obs)                        -> logits [B, V] at the last prompt position,
                                                 hidden [B, P, D], embeddings [B, P, D], cache
  prefill_with_block(params, obs, tokens, depth, intra)
                                              -> the same, with block logits [B, T, V], block
                                                 hidden [B, T, D] and the block (one pass)
  cached_pass(params, cache, tokens, depth, intra)
                                              -> logits [B, T, V], hidden [B, T, D], block:
                                                 T tokens against the cache, which is unchanged
  commit(cache, block, src, n)                -> the cache with the block's tokens at offsets
                                                 src[b, :n[b]] appended, in that order
  select_cache(rows, new, old)                -> per row: `new` where rows [B] holds, else `old`
  embed_tokens(params, tokens), action_head(params, hidden) -> [..., D], [..., 256]
  cfg                                         -> the architecture record (`vla.VLAConfig`):
                                                 token ids, prompt length and widths, which a
                                                 drafter of this target is built from

A block is laid out by `depth` [B, T] (each token's position offset from the committed
sequence's end) and `intra` [B, T, T] (which block tokens each may attend to, besides all
committed ones): causal for AR, ancestors for a tree. The cache and the block are the
model's own pytrees: their layout is nobody else's business.

`VLATarget` is the shipped VLA (`heisd_jax.vla`, a KV cache of fixed slots). A target is
any hashable object with these members (so it can be a static jit argument); every public
decoding function takes one wherever it takes a `vla.VLAConfig` (`as_target`).
`tests/test_target_model.py` plugs in a second one, with no KV cache at all.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax
import jax.numpy as jnp

from heisd_jax import vla
from heisd_jax.observation import Observation
from heisd_jax.tokenizer import ACTION_DIM


class TargetModel(Protocol):
    """What a decoder needs of a target VLA (the module doc gives each member's contract)."""

    cfg: vla.VLAConfig

    def prefill(self, params, obs: Observation): ...

    def prefill_with_block(self, params, obs: Observation, tokens, depth, intra): ...

    def cached_pass(self, params, cache, tokens, depth, intra): ...

    def commit(self, cache, block, src, n): ...

    def select_cache(self, rows, new, old): ...

    def embed_tokens(self, params, tokens): ...

    def action_head(self, params, hidden): ...


Model = vla.VLAConfig | TargetModel  # what the decoders accept: a config is its `VLATarget`


@dataclasses.dataclass(frozen=True)
class VLATarget:
    """The shipped VLA behind the interface: a KV cache of `cfg.cache_slots` slots."""

    cfg: vla.VLAConfig

    def prefill(self, params, obs: Observation):
        return vla.prefill_features(params, self.cfg, obs)

    def prefill_with_block(self, params, obs: Observation, tokens, depth, intra):
        return vla.prefill_with_block(params, self.cfg, obs, tokens, depth, intra)

    def cached_pass(self, params, cache: vla.KVCache, tokens, depth, intra):
        return vla.cached_pass(params, self.cfg, cache, tokens, depth, intra)

    def commit(self, cache: vla.KVCache, block: vla.Block, src, n) -> vla.KVCache:
        return vla.commit(cache, block, src, n)

    def select_cache(self, rows, new: vla.KVCache, old: vla.KVCache) -> vla.KVCache:
        return vla.select_cache(rows, new, old)

    def embed_tokens(self, params, tokens):
        return vla.embed_tokens(params, tokens)

    def action_head(self, params, hidden):
        return vla.action_head(params, self.cfg, hidden)


def as_target(model: Any) -> TargetModel:
    """`model` itself if it is a target, else the shipped VLA of config `model`."""
    if isinstance(model, vla.VLAConfig):
        return VLATarget(model)
    missing = [m for m in ("cfg", "prefill", "prefill_with_block", "cached_pass", "commit", "select_cache",
                           "embed_tokens", "action_head") if not hasattr(model, m)]
    if missing:
        raise TypeError(f"{type(model).__name__} is neither a vla.VLAConfig nor a TargetModel (missing {missing})")
    return model


def select_rows(rows: jnp.ndarray, new, old):
    """Per row of any pytree whose leaves have the batch on axis 0: `new` where rows [B]."""
    return jax.tree.map(lambda n, o: jnp.where(rows.reshape((-1,) + (1,) * (n.ndim - 1)), n, o), new, old)


def greedy_ids(cfg: vla.VLAConfig, logits: jnp.ndarray) -> jnp.ndarray:
    """The greedy action token ids of logits [..., V] (the best of the 256 action ids)."""
    return jnp.argmax(vla.action_logits(cfg, logits), -1) + cfg.first_action_id


def ar_decode(params, model, obs: Observation):
    """Greedy autoregressive decoding of one action (the `ar` baseline): 1 prefill + 6
    single-token passes. Returns action token ids [B, 7] and the number of target passes."""
    t = as_target(model)
    vla.check_observation(t.cfg, obs)
    logits, _, _, cache = t.prefill(params, obs)
    first = greedy_ids(t.cfg, logits)  # [B]
    b = first.shape[0]
    zero, causal1 = jnp.zeros((b, 1), jnp.int32), jnp.ones((b, 1, 1), bool)

    def next_token(carry, _):
        cache, tok = carry
        lg, _, blk = t.cached_pass(params, cache, tok[:, None], zero, causal1)
        cache = t.commit(cache, blk, zero, jnp.ones((b,), jnp.int32))
        nxt = greedy_ids(t.cfg, lg[:, 0])
        return (cache, nxt), nxt

    _, rest = jax.lax.scan(next_token, (cache, first), None, length=ACTION_DIM - 1,
                           unroll=ACTION_DIM - 1 if t.cfg.unroll else 1)
    return jnp.concatenate([first[:, None], rest.T], 1), ACTION_DIM


def ar_action(params, model, obs: Observation) -> tuple[jnp.ndarray, dict[str, jnp.ndarray]]:
    """`ar_decode` with the per-row statistics every decoding method reports: (tokens [B, 7],
    {"target_passes", "tokens"}, each [B] float32)."""
    tokens, passes = ar_decode(params, model, obs)
    b = tokens.shape[0]
    return tokens, {"target_passes": jnp.full((b,), passes, jnp.float32),
                    "tokens": jnp.full((b,), ACTION_DIM, jnp.float32)}


def ar_continue(params, model, cache, out: jnp.ndarray, n_out: jnp.ndarray):
    """Greedy AR decoding of the rest of a partly decoded action: out [B, 7] token ids
    (valid j < n_out [B], 1..7), the cache holding the prompt and out[:, :n_out - 1] (the
    last emitted token is not fed yet). One single-token pass per step until every row
    holds 7 tokens (a `lax.while_loop`: the batch runs until its longest row is done; rows
    already done are masked). Returns out [B, 7] and the passes each row needed [B]."""
    t = as_target(model)
    b = out.shape[0]
    zero, causal1 = jnp.zeros((b, 1), jnp.int32), jnp.ones((b, 1, 1), bool)
    rows = jnp.arange(b)

    def body(carry):
        cache, out, n_out, passes = carry
        active = n_out < ACTION_DIM
        last = out[rows, jnp.clip(n_out - 1, 0, ACTION_DIM - 1)]
        lg, _, blk = t.cached_pass(params, cache, last[:, None], zero, causal1)
        cache = t.commit(cache, blk, zero, active.astype(jnp.int32))
        out = out.at[rows, jnp.where(active, n_out, ACTION_DIM)].set(greedy_ids(t.cfg, lg[:, 0]), mode="drop")
        return cache, out, n_out + active, passes + active

    _, out, _, passes = jax.lax.while_loop(lambda c: jnp.any(c[2] < ACTION_DIM), body,
                                           (cache, out, n_out.astype(jnp.int32), jnp.zeros((b,), jnp.int32)))
    return out, passes

