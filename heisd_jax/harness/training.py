"""Training the VLA with teacher forcing: cross-entropy on the 7 action tokens.

Optionally with ordinal label smoothing (`label_sigma_bins` > 0): the target of each action
token is a discretised Gaussian over neighbouring bins instead of a one-hot, so a guess one
bin off costs less than one 100 bins off (as in "HL-Gauss", Farebrother et al. 2024). The
mode stays the labelled bin, so greedy decoding is unchanged in expectation; 0 gives
OpenVLA's plain cross-entropy.

`make_train_step` returns a pure step (state, table, key) -> (state, metrics) that draws
its own minibatch from the device-resident step table. AdamW with linear warm-up and cosine
decay (optax).

The step runs as two compiled programs: the draw (gather and augmentation, whose program
depends on the table's length) and the update (loss, gradient and AdamW on the drawn
minibatch), whose program depends neither on the table nor on what a build changes from
round to round: the learning rate, its warm-up and length, and the label width are inputs
(`round_settings`). A build's DAgger rounds train on a table that grows every round, with
other settings than its first policy; each round after the first finds the update's program
in the persistent compilation cache, and compiles only the draw.

Data parallelism (`mesh`, a one-axis `jax.sharding.Mesh`): the state and the step table are
replicated on every device, the drawn minibatch is split over the mesh (each device gathers
and differentiates its own rows), and XLA's SPMD partitioner inserts the gradient
all-reduce. The step computes the same function as on one device (the same rows, the same
mean), up to the order of the gradient's summation.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from heisd_jax import drafter, target_model, vla, xla_options
from heisd_jax.harness import data
from heisd_jax.tokenizer import ACTION_DIM, ActionTokenizer


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    steps: int = 8000
    batch_size: int = 256
    lr: float = 3e-4
    warmup_steps: int = 500
    weight_decay: float = 0.05
    grad_clip: float = 1.0
    label_sigma_bins: float = 0.0  # ordinal label smoothing (0: one-hot targets, as OpenVLA)
    image_shift: int = 0  # random-shift augmentation of the camera image, pixels
    seed: int = 0
    deterministic: bool = True  # compile the step with xla_options.DETERMINISTIC (GPU run-to-run determinism)
    # The teacher-forced sequence padded to a multiple of this (`action_loss`: the same loss): 16 turns
    # a build's 156 tokens into 160, a shape whose products suit the GPU's matrix units better
    # (`experiments.studies.train_step` times it against its `unpadded` variant).
    seq_multiple: int = 16

    def __post_init__(self):
        if self.steps < 1 or self.batch_size < 1 or self.lr <= 0:
            raise ValueError(f"steps, batch_size and lr must be positive: {self}")
        if not 0 <= self.warmup_steps < self.steps:
            raise ValueError(f"warmup_steps must be in [0, steps): {self.warmup_steps} vs {self.steps}")
        if self.image_shift < 0:
            raise ValueError(f"image_shift must be >= 0, got {self.image_shift}")
        if self.label_sigma_bins < 0:
            raise ValueError(f"label_sigma_bins must be >= 0, got {self.label_sigma_bins}")
        if self.seq_multiple < 1:
            raise ValueError(f"seq_multiple must be >= 1, got {self.seq_multiple}")


@struct.dataclass
class TrainState:
    step: jnp.ndarray
    params: dict
    opt_state: optax.OptState


END_LR_FRACTION = 0.05  # the cosine decay ends at this fraction of the peak learning rate


def round_settings(cfg: TrainConfig) -> dict:
    """The settings a build changes from one training round to the next (learning rate, its
    warm-up and length, label width), as float32 scalars: the update takes them as inputs
    rather than constants, so every round of a build runs one compiled program."""
    return {k: jnp.float32(getattr(cfg, k)) for k in ("lr", "warmup_steps", "steps", "label_sigma_bins")}


def lr_schedule(peak, warmup_steps, steps):
    """optax.warmup_cosine_decay_schedule(0, peak, warmup_steps, steps, peak * END_LR_FRACTION)
    in jnp, so that its settings may be traced values: linear warm-up from 0, then a cosine
    decay to END_LR_FRACTION of the peak at `steps`."""
    def schedule(count):
        count = jnp.asarray(count, jnp.float32)
        warm = peak * count / jnp.maximum(warmup_steps, 1.0)
        t = jnp.minimum(count - warmup_steps, steps - warmup_steps) / (steps - warmup_steps)
        decay = peak * ((1 - END_LR_FRACTION) * 0.5 * (1 + jnp.cos(jnp.pi * t)) + END_LR_FRACTION)
        return jnp.where(count < warmup_steps, warm, decay)

    return schedule


def optimizer(cfg: TrainConfig, settings: dict | None = None) -> optax.GradientTransformation:
    """AdamW with gradient clipping and `lr_schedule`, at `settings` (`round_settings`, possibly
    traced; `cfg`'s own by default). The optimizer's state does not depend on them."""
    st = round_settings(cfg) if settings is None else settings
    schedule = lr_schedule(st["lr"], st["warmup_steps"], st["steps"])
    return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), optax.adamw(schedule, weight_decay=cfg.weight_decay))


def init_state(model_cfg: vla.VLAConfig, cfg: TrainConfig) -> TrainState:
    params = vla.init_params(model_cfg, jax.random.PRNGKey(cfg.seed))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer(cfg).init(params))


def continue_from(model_cfg: vla.VLAConfig, cfg: TrainConfig, params) -> TrainState:
    """A fresh training state (step 0, a new optimizer state) around `params` (a policy
    checkpoint's, e.g. a DAgger round's starting point), cast to `init_state`'s dtypes: the
    float32 master weights. A policy stored in bfloat16 would otherwise make the master weights
    bfloat16, where the optimizer's small updates round away (and optax keeps each parameter's
    dtype). It equals `init_state`'s state with its parameters replaced, but draws no random
    initialisation only to discard it: one compiled program, where the eager draw runs (and on
    a GPU compiles) one small program per parameter."""
    own = jax.eval_shape(lambda: init_state(model_cfg, cfg))

    def make(params):
        params = jax.tree.map(lambda new, like: jnp.asarray(new, like.dtype), params, own.params)
        return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer(cfg).init(params))

    return jax.jit(make)(params)


def soft_bin_targets(bins: jnp.ndarray, n_bins: int, sigma) -> jnp.ndarray:
    """[..., n_bins] target distributions: a Gaussian of std `sigma` bins around each bin
    (one-hot where sigma is 0; sigma may be a traced value)."""
    d = jnp.arange(n_bins) - bins[..., None]
    w = jnp.exp(-0.5 * (d / jnp.where(sigma > 0, sigma, 1.0)) ** 2)
    return jnp.where(sigma > 0, w / w.sum(-1, keepdims=True), jax.nn.one_hot(bins, n_bins))


def action_loss(params, model_cfg: vla.VLAConfig, obs: vla.Observation, tokens: jnp.ndarray,
                label_sigma_bins: float = 0.0, seq_multiple: int = 1):
    """Mean cross-entropy of the action tokens given the prompt and the previous tokens, and
    metrics per action dimension [7]: greedy token accuracy, mean absolute bin error, and the
    share of tokens whose greedy bin has probability > 0.5 ("decisive": drafts and retrieved
    actions are accepted where the target's choice is clear, not a near tie).

    The output head runs from the first action position on (not at the prompt's positions
    before it, whose logits the loss never reads). `seq_multiple`: the sequence
    (prompt + 7 tokens) is padded to a multiple of it with copies of the last token, which no
    earlier position attends to (causal attention): the same loss, at shapes whose products
    may run on better-aligned kernels (`experiments.studies.train_step` measures it)."""
    p = model_cfg.prompt_len
    pad = -(p + tokens.shape[1]) % seq_multiple
    inputs = jnp.concatenate([tokens, jnp.repeat(tokens[:, -1:], pad, 1)], 1) if pad else tokens
    logits, _ = vla.forward(params, model_cfg, obs, inputs, training=True, logits_from=p - 1)
    pred = vla.action_logits(model_cfg, logits[:, :ACTION_DIM])  # [B, 7, 256]
    target = tokens - model_cfg.first_action_id
    soft = soft_bin_targets(target, pred.shape[-1], label_sigma_bins)
    loss = optax.softmax_cross_entropy(pred, soft).mean()
    greedy = jnp.argmax(pred, -1)
    return loss, {"token_acc": jnp.mean(greedy == target, axis=0),
                  "bin_err": jnp.mean(jnp.abs(greedy - target), axis=0),
                  "decisive": jnp.mean(jax.nn.softmax(pred.astype(jnp.float32), -1).max(-1) > 0.5, axis=0)}


def _jit(cfg: TrainConfig):
    """jax.jit, with `xla_options.DETERMINISTIC` where `cfg.deterministic`: for the training steps
    and their held-out evaluations, so a rerun gives the same parameters and logs the same figures."""
    return functools.partial(jax.jit, compiler_options=xla_options.determinism(cfg.deterministic))


def _rows(mesh: Mesh) -> NamedSharding:
    """Rows split over the mesh's one axis."""
    return NamedSharding(mesh, P(mesh.axis_names[0]))


def _check_split(mesh: Mesh | None, cfg: TrainConfig):
    if mesh is not None and cfg.batch_size % mesh.size:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by the {mesh.size} devices it is split over; "
                         f"use a multiple of {mesh.size}")


def _draw_program(draw, mesh: Mesh | None, cfg: TrainConfig):
    """`draw` (-> a minibatch) jitted; with a mesh, its rows come out split over the mesh."""
    return _jit(cfg)(draw) if mesh is None else _jit(cfg)(draw, out_shardings=_rows(mesh))


def _update_program(update, mesh: Mesh | None, cfg: TrainConfig, n_replicated: int):
    """`update`(state, *replicated, batch) jitted; with a mesh, the state, the other replicated
    inputs and the outputs replicated over the mesh, the batch split over it."""
    if mesh is None:
        return _jit(cfg)(update)
    whole = NamedSharding(mesh, P())
    return _jit(cfg)(update, in_shardings=(whole,) * (1 + n_replicated) + (_rows(mesh),), out_shardings=whole)


def _apply(opt, state: TrainState, grads) -> TrainState:
    updates, opt_state = opt.update(grads, state.opt_state, state.params)
    return TrainState(step=state.step + 1, params=optax.apply_updates(state.params, updates), opt_state=opt_state)


def make_train_step(model_cfg: vla.VLAConfig, cfg: TrainConfig, tok: ActionTokenizer, mesh: Mesh | None = None):
    """(state, table, key) -> (state, metrics), over the devices of `mesh` if given (data
    parallel; the state and table then live replicated on the mesh). Two programs, kept as
    the step's attributes: `draw`(table, step, key) -> minibatch, and `update`(state,
    settings, minibatch) -> (state, metrics), whose program is the same for any table and
    any `round_settings` (`settings`: this step's)."""
    _check_split(mesh, cfg)
    settings = round_settings(cfg)

    def draw(table: data.StepTable, step, key):
        return data.sample_batch(table, jax.random.fold_in(key, step), cfg.batch_size, tok, cfg.image_shift,
                                 model_cfg.n_views)

    def update(state: TrainState, settings: dict, batch):
        obs, tokens = batch
        (loss, metrics), grads = jax.value_and_grad(action_loss, has_aux=True)(
            state.params, model_cfg, obs, tokens, settings["label_sigma_bins"], cfg.seq_multiple)
        return _apply(optimizer(cfg, settings), state, grads), {"loss": loss, **metrics}

    draw_fn, update_fn = _draw_program(draw, mesh, cfg), _update_program(update, mesh, cfg, 1)

    def train_step(state: TrainState, table: data.StepTable, key: jax.Array):
        return update_fn(state, settings, draw_fn(table, state.step, key))

    train_step.draw, train_step.update, train_step.settings = draw_fn, update_fn, settings  # the two programs
    return train_step


def make_eval_fn(model_cfg: vla.VLAConfig, tok: ActionTokenizer, batch: int, cfg: TrainConfig):
    """(params, table, key) -> (loss, metrics) on a random `batch` of the table's steps, with
    `cfg`'s label smoothing (an input of the compiled program, as in the update)."""
    def evaluate(params, table: data.StepTable, key: jax.Array, sigma):
        obs, tokens = data.sample_batch(table, key, batch, tok)
        return action_loss(params, model_cfg, obs, tokens, sigma)

    program, sigma = _jit(cfg)(evaluate), round_settings(cfg)["label_sigma_bins"]
    return lambda params, table, key: program(params, table, key, sigma)


# --- the drafter (EAGLE), trained against a frozen target ---------------------------------

def greedy_tokens(tparams, model_cfg: vla.VLAConfig, table: data.StepTable, batch: int = 1024) -> jnp.ndarray:
    """The target's greedy action tokens [N, 7] for every step of the table: the drafter
    learns to predict the target's own choices (what verification will compare against)."""
    run = jax.jit(lambda p, obs: target_model.ar_decode(p, model_cfg, obs)[0])
    out = []
    for start in range(0, table.size, batch):
        i = jnp.minimum(jnp.arange(start, start + batch), table.size - 1)
        obs = vla.Observation(image=table.image[i], instruction=table.instruction[i], proprio=table.proprio[i])
        out.append(run(tparams, obs))
    return jnp.concatenate(out)[: table.size]


def init_drafter_state(model_cfg: vla.VLAConfig, cfg: TrainConfig) -> TrainState:
    params = drafter.init_params(model_cfg, jax.random.PRNGKey(cfg.seed))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer(cfg).init(params))


def make_drafter_step(model_cfg: vla.VLAConfig, cfg: TrainConfig, mesh: Mesh | None = None):
    """(state, tparams, table, tokens, key) -> (state, metrics): EAGLE's loss on a random
    minibatch of steps teacher-forced on the target's greedy tokens; two programs and data
    parallel over `mesh` as `make_train_step`."""
    _check_split(mesh, cfg)
    settings = round_settings(cfg)

    def draw(table: data.StepTable, tokens, step, key):
        k_idx, k_shift = jax.random.split(jax.random.fold_in(key, step))
        i = data.draw_rows(table, k_idx, cfg.batch_size)
        obs = vla.Observation(image=data.random_shift(table.image[i], k_shift, cfg.image_shift, model_cfg.n_views),
                              instruction=table.instruction[i], proprio=table.proprio[i])
        return obs, tokens[i]

    def update(state: TrainState, settings: dict, tparams, batch):
        obs, labels = batch
        (loss, metrics), grads = jax.value_and_grad(drafter.loss, has_aux=True)(state.params, tparams, model_cfg, obs,
                                                                                labels)
        return _apply(optimizer(cfg, settings), state, grads), {"loss": loss, **metrics}

    draw_fn, update_fn = _draw_program(draw, mesh, cfg), _update_program(update, mesh, cfg, 2)

    def step(state: TrainState, tparams, table: data.StepTable, tokens, key):
        return update_fn(state, settings, tparams, draw_fn(table, tokens, state.step, key))

    return step


def make_drafter_eval(model_cfg: vla.VLAConfig, batch: int, cfg: TrainConfig):
    def evaluate(dparams, tparams, table: data.StepTable, tokens, key):
        i = jax.random.randint(key, (batch,), 0, table.size)
        obs = vla.Observation(image=table.image[i], instruction=table.instruction[i], proprio=table.proprio[i])
        return drafter.loss(dparams, tparams, model_cfg, obs, tokens[i])

    return _jit(cfg)(evaluate)
