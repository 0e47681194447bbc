"""Training the VLA with teacher forcing: cross-entropy on the 7 action tokens.

`make_train_step` returns a jitted pure step (state, table, key) -> (state, metrics) that
draws its own minibatch from the device-resident step table. AdamW with linear warm-up and
cosine decay (optax).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax
from flax import struct

from heisd_jax import data, vla
from heisd_jax.tokenizer import ACTION_DIM, ActionTokenizer


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    steps: int = 8000
    batch_size: int = 256
    lr: float = 3e-4
    warmup_steps: int = 500
    weight_decay: float = 0.05
    grad_clip: float = 1.0
    seed: int = 0

    def __post_init__(self):
        if self.steps < 1 or self.batch_size < 1 or self.lr <= 0:
            raise ValueError(f"steps, batch_size and lr must be positive: {self}")
        if not 0 <= self.warmup_steps < self.steps:
            raise ValueError(f"warmup_steps must be in [0, steps): {self.warmup_steps} vs {self.steps}")


@struct.dataclass
class TrainState:
    step: jnp.ndarray
    params: dict
    opt_state: optax.OptState


def optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    schedule = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, cfg.warmup_steps, cfg.steps, end_value=cfg.lr * 0.05)
    return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), optax.adamw(schedule, weight_decay=cfg.weight_decay))


def init_state(model_cfg: vla.VLAConfig, cfg: TrainConfig) -> TrainState:
    params = vla.init_params(model_cfg, jax.random.PRNGKey(cfg.seed))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer(cfg).init(params))


def action_loss(params, model_cfg: vla.VLAConfig, obs: vla.Observation, tokens: jnp.ndarray):
    """Mean cross-entropy of the action tokens given the prompt and the previous tokens, and
    the per-dimension greedy token accuracy [7]."""
    logits, _ = vla.forward(params, model_cfg, obs, tokens)
    p = model_cfg.prompt_len
    pred = vla.action_logits(model_cfg, logits[:, p - 1: p - 1 + ACTION_DIM])  # [B, 7, 256]
    target = tokens - model_cfg.first_action_id
    loss = optax.softmax_cross_entropy_with_integer_labels(pred, target).mean()
    acc = jnp.mean(jnp.argmax(pred, -1) == target, axis=0)
    return loss, acc


def make_train_step(model_cfg: vla.VLAConfig, cfg: TrainConfig, tok: ActionTokenizer):
    opt = optimizer(cfg)

    @jax.jit
    def train_step(state: TrainState, table: data.StepTable, key: jax.Array):
        obs, tokens = data.sample_batch(table, jax.random.fold_in(key, state.step), cfg.batch_size, tok)
        (loss, acc), grads = jax.value_and_grad(action_loss, has_aux=True)(state.params, model_cfg, obs, tokens)
        updates, opt_state = opt.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return TrainState(step=state.step + 1, params=params, opt_state=opt_state), {"loss": loss, "token_acc": acc}

    return train_step


def make_eval_fn(model_cfg: vla.VLAConfig, tok: ActionTokenizer, batch: int):
    @jax.jit
    def evaluate(params, table: data.StepTable, key: jax.Array):
        obs, tokens = data.sample_batch(table, key, batch, tok)
        return action_loss(params, model_cfg, obs, tokens)

    return evaluate
