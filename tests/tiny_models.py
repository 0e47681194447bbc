"""Tiny random VLA/drafter models and observations shared by the decoding tests."""

import jax
import jax.numpy as jnp
import numpy as np

from heisd_jax import drafter, target_model, vla

CFG = vla.VLAConfig(image_size=16, patch_size=8, vision_layers=1, d_model=32, n_layers=2, n_heads=4, mlp_dim=64,
                    cache_slots=128)
HYBRID_B = 6  # the batch of the hybrid tests (one row per retrieval case of `candidates`)


def obs(seed=0, batch=4):
    rng = np.random.default_rng(seed)
    instr = rng.integers(1, CFG.text_vocab, (batch, CFG.text_len))
    instr[:, 12:] = 0
    return vla.Observation(image=jnp.asarray(rng.integers(0, 256, (batch, 16, 16, 3)), jnp.uint8),
                           instruction=jnp.asarray(instr, jnp.int32),
                           proprio=jnp.asarray(rng.normal(size=(batch, 8)), jnp.float32))


def aligned_pair(noise: float):
    """A target whose decoder blocks add nothing (hidden = norm(input embedding)) and a
    drafter that copies the token embedding through the same norm: the drafter predicts the
    target's features exactly (noise = 0), or approximately (noise > 0: partial acceptance)."""
    tp = vla.init_params(CFG, jax.random.PRNGKey(2))
    tp = dict(tp, blocks=dict(tp["blocks"], out={"kernel": jnp.zeros_like(tp["blocks"]["out"]["kernel"])},
                              mlp=dict(tp["blocks"]["mlp"], down={"kernel": jnp.zeros_like(tp["blocks"]["mlp"]["down"]["kernel"])})))
    dp = drafter.init_params(CFG, jax.random.PRNGKey(3))
    d = CFG.d_model
    fc = jnp.concatenate([jnp.eye(d), jnp.zeros((d, d))]) + noise * jax.random.normal(jax.random.PRNGKey(4), (2 * d, d))
    block = dict(dp["block"], out={"kernel": jnp.zeros((d, d))},
                 mlp=dict(dp["block"]["mlp"], down={"kernel": jnp.zeros_like(dp["block"]["mlp"]["down"]["kernel"])}))
    return tp, dict(dp, fc={"kernel": fc, "bias": jnp.zeros(d)}, block=block)


_ar = jax.jit(lambda t, o: target_model.ar_decode(t, CFG, o)[0])  # one program per batch shape, shared by every test


def ar(tp, obs):
    """Greedy AR action tokens [B, 7] (the reference every lossless method must equal)."""
    return _ar(tp, obs)


def candidates(ar_tokens, rng):
    """Per row: candidate 0 = the AR action with its tokens from `cut` on replaced (cut 7 =
    the AR action itself), the others random."""
    cand = rng.integers(CFG.first_action_id, CFG.first_action_id + 256, (HYBRID_B, 3, 7))
    cuts = np.array([7, 0, 3, 5, 1, 7])
    for b, cut in enumerate(cuts):
        cand[b, 1, :cut] = ar_tokens[b, :cut]
        if cut < 7:
            cand[b, 1, cut] = CFG.first_action_id + (ar_tokens[b, cut] - CFG.first_action_id + 128) % 256
    return jnp.asarray(cand, jnp.int32), cuts
