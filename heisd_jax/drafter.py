"""The EAGLE feature-level drafter (Spec-VLA's drafter for OpenVLA).

One Llama decoder layer over `Linear(concat(token embedding, feature))`: the entry at
position i reads the embedding of the input at position i+1 and the target's last-layer
hidden state at i, and predicts the hidden state at i+1; the target's output head (frozen,
reused) turns a predicted feature into next-token logits. The drafter keeps its own
one-layer KV cache over the prompt (visual, instruction and proprio features, as Spec-VLA)
and the accepted action tokens. Inside a draft tree, predicted features stand in for the
target's.

Pure functions of (drafter params, target params, cache, inputs), like `vla`:
    prompt_pass(...)      the prompt's P entries into a fresh drafter cache
    cached_pass(...)      T entries written at given slots with an explicit attention mask
    loss(...)             EAGLE's training loss on a teacher-forced sequence
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from heisd_jax import vla
from heisd_jax.tokenizer import ACTION_DIM


def init_cache(cfg: vla.VLAConfig, batch: int) -> vla.KVCache:
    """A one-layer cache with the target's geometry."""
    return vla.init_cache(vla.VLAConfig(**{**cfg.__dict__, "n_layers": 1}), batch)


class Drafter(nn.Module):
    cfg: vla.VLAConfig

    @nn.compact
    def __call__(self, emb, feat, layer_k, layer_v, positions, cache_mask, block_mask):
        """emb, feat [B, T, D] -> predicted features [B, T, D], the entries' (k, v)."""
        x = nn.Dense(self.cfg.d_model, use_bias=True, dtype=self.cfg.dtype, name="fc")(
            jnp.concatenate([emb, feat.astype(emb.dtype)], -1))
        x, (k, v) = vla.DecoderBlock(self.cfg, name="block")(x, layer_k, layer_v, vla.rotary_angles(self.cfg, positions),
                                                   cache_mask, block_mask)
        return nn.RMSNorm(epsilon=self.cfg.norm_eps, dtype=self.cfg.dtype, name="norm")(x), (k, v)


def init_params(cfg: vla.VLAConfig, key: jax.Array) -> dict:
    b, t, s = 1, 2, cfg.cache_slots
    hd = cfg.d_model // cfg.n_heads
    z = jnp.zeros((b, t, cfg.d_model))
    kv = jnp.zeros((b, s, cfg.n_heads, hd), cfg.dtype)
    return Drafter(cfg).init(key, z, z, kv, kv, jnp.zeros((b, t), jnp.int32), jnp.ones((b, t, s), bool),
                             jnp.ones((b, t, t), bool))["params"]


@vla.at_config_precision
def cached_pass(dparams, cfg: vla.VLAConfig, cache: vla.KVCache, emb, feat, positions, write_slot, mask):
    """T entries against the drafter cache, their keys/values written at slots
    write_slot..write_slot+T-1 (key_mask/length unchanged). mask [B, T, S] says which slots
    each entry attends to (its own slot included). Returns features [B, T, D] and the cache."""
    t = emb.shape[1]
    own = write_slot[:, None] + jnp.arange(t)[None]  # [B, T] the entries' slots
    rel = jnp.arange(cfg.cache_slots)[None] - write_slot[:, None]
    in_block = (rel >= 0) & (rel < t)  # [B, S] slots the entries overwrite
    block_mask = jnp.take_along_axis(mask, jnp.broadcast_to(own[:, None, :], (own.shape[0], t, t)), 2)
    out, (k, v) = Drafter(cfg).apply({"params": dparams}, emb, feat, cache.k[0], cache.v[0], positions,
                                     mask & ~in_block[:, None], block_mask)
    write = jax.vmap(lambda c, new, s: jax.lax.dynamic_update_slice(c, new.astype(c.dtype), (s, 0, 0)))
    return out, cache.replace(k=write(cache.k[0], k, write_slot)[None], v=write(cache.v[0], v, write_slot)[None])


def _causal_pass(dparams, cfg: vla.VLAConfig, emb, feat, key_ok):
    """Entries 0..T-1 (emb, feat [B, T, D]) causally into a fresh drafter cache, each
    attending to the earlier entries whose key_ok [B, T] holds, and to itself."""
    b, t, _ = emb.shape
    slots = jnp.arange(cfg.cache_slots)
    slot_ok = vla.pad_to(key_ok, cfg.cache_slots)
    mask = (vla.causal_mask(t, cfg.cache_slots)[None] & slot_ok[:, None, :]) | (slots[None, None, :] == jnp.arange(t)[None, :, None])
    positions = jnp.broadcast_to(jnp.arange(t), (b, t))
    out, cache = cached_pass(dparams, cfg, init_cache(cfg, b), emb, feat, positions, jnp.zeros((b,), jnp.int32), mask)
    return out, cache.replace(key_mask=slot_ok, length=jnp.full((b,), t, jnp.int32))


def prompt_pass(dparams, cfg: vla.VLAConfig, prompt_x, prompt_hidden, key_ok, first_token_emb):
    """The drafter's prefill: entries i = 0..P-1 read (x_{i+1}, h_i), with x_P the embedding
    of the first action token (the target's prefill choice). Returns the feature predicted
    for the first action token's position [B, D] and the cache (length P)."""
    emb = jnp.concatenate([prompt_x[:, 1:], first_token_emb[:, None]], 1)
    out, cache = _causal_pass(dparams, cfg, emb, prompt_hidden, key_ok)
    return out[:, -1], cache


def teacher_forced(dparams, cfg: vla.VLAConfig, x, hidden, key_ok):
    """Drafter over a whole sequence: x, hidden [B, N, D] (target input embeddings and
    last-layer states), key_ok [B, N]. Entry i reads (x_{i+1}, h_i); returns the predicted
    features of positions 1..N-1 [B, N-1, D]."""
    return _causal_pass(dparams, cfg, x[:, 1:], hidden[:, :-1], key_ok[:, :-1])[0]


def target_sequence(tparams, cfg: vla.VLAConfig, obs: vla.Observation, tokens):
    """The target's input embeddings, last-layer hidden states and key mask over prompt +
    the 7 action tokens [B, P+7, D] (teacher forced on `tokens`)."""
    _, hidden = vla.forward(tparams, cfg, obs, tokens)
    prompt_x = vla.prompt_embeddings(tparams, cfg, obs)
    x = jnp.concatenate([prompt_x, vla.embed_tokens(tparams, tokens).astype(prompt_x.dtype)], 1)
    key_ok = jnp.concatenate([vla.prompt_key_mask(cfg, obs.instruction), jnp.ones(tokens.shape, bool)], 1)
    return x, hidden, key_ok


def loss(dparams, tparams, cfg: vla.VLAConfig, obs: vla.Observation, tokens, reg_weight=1.0, ce_weight=0.1):
    """EAGLE's loss: smooth-L1 regression of the target's next hidden state (every
    position) + cross-entropy of the target head on the predicted features against the next
    action token (tokens [B, 7]: the target's own greedy tokens). Returns (loss, metrics)
    with the drafter's top-1 accuracy per predicted action token (a_1..a_6) [6]."""
    x, hidden, key_ok = target_sequence(tparams, cfg, obs, tokens)
    x, hidden = jax.lax.stop_gradient(x), jax.lax.stop_gradient(hidden)
    pred = teacher_forced(dparams, cfg, x, hidden, key_ok).astype(jnp.float32)  # features of positions 1..N-1
    target = hidden[:, 1:].astype(jnp.float32)
    w = key_ok[:, 1:].astype(jnp.float32)
    err = jnp.abs(pred - target)
    smooth_l1 = jnp.where(err < 1.0, 0.5 * err ** 2, err - 0.5).mean(-1)
    reg = (smooth_l1 * w).sum() / w.sum()
    p = cfg.prompt_len
    # Features at the positions of a_0..a_5 (pred index = position - 1) predict a_1..a_6.
    feats = pred[:, p - 1: p - 1 + ACTION_DIM - 1]
    logits = vla.action_head(jax.lax.stop_gradient(tparams), cfg, feats)
    labels = tokens[:, 1:] - cfg.first_action_id
    ce = -jnp.take_along_axis(jax.nn.log_softmax(logits), labels[..., None], -1).mean()
    acc = jnp.mean(jnp.argmax(logits, -1) == labels, axis=0)
    return reg_weight * reg + ce_weight * ce, {"reg": reg, "ce": ce, "top1": acc}
