"""The target VLA, in OpenVLA's mould: a small ViT on the camera image, the instruction as
text tokens, proprioception as one token, and a Llama-style causal decoder (RMSNorm, rotary
positions, SwiGLU) emitting the action's 7 tokens from the last 256 vocabulary ids.

Everything is a pure function of (params, cache, inputs):
    prefill(params, cfg, obs)                     prompt pass -> logits, hidden, cache
    cached_pass(params, cfg, cache, tokens, ...)  T tokens against the cache (AR: T = 1;
                                                  tree verification: T nodes + tree mask)
                                                  -> logits, hidden, their keys/values
    commit(cache, block, src, n)                  write n of those tokens into the cache
Decoders reach these through `heisd_jax.target_model.VLATarget` (the target-model
interface), which also holds greedy AR over them (`target_model.ar_decode`); the public
entry that also speculates is `spec_decode.decode_action`.
The KV cache has a static number of slots; each row has its own length and key mask, so
rows can accept different numbers of tokens. A pass never writes the cache: attention
reads the committed slots and the pass's own block (`Block`) side by side, and `commit`
scatters only the kept tokens' keys/values into the cache, in place. (Writing the block
into the cache inside the pass makes XLA copy the whole cache on every pass: at batch 1,024
on an H200 that is half of AR's time, `experiments/studies/trace_decode.py` shows it.) Vocabulary: text
ids [0, text_vocab), action ids [text_vocab, text_vocab + 256).

Matrix products of a float32 model run in full float32 (`VLAConfig.matmul_precision`), so the
same state decodes to the same tokens at every batch size: XLA's default on recent NVIDIA
GPUs runs some shapes on TF32 tensor cores (10-bit mantissa) and others not, and the logits
of one state at batch 1 and at batch 256 then differ by enough to flip a greedy token whose
two largest logits are that close (docs/target.md has the measurement).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from heisd_jax import invariant_products, rounded_products
from heisd_jax.observation import PAD_ID, TEXT_LEN, TEXT_VOCAB, Observation
from heisd_jax.tokenizer import ACTION_DIM, INVALID_ID, N_BINS

NEG_INF = -1e9
ATTENTIONS = ("xla", "cudnn")  # VLAConfig.attention
PATCHIFIES = ("conv", "dense")  # VLAConfig.patchify
FUSED_ATTENTION_DTYPES = ("bfloat16", "float16")  # the dtypes cuDNN's fused attention computes in
AUTO_ATTENTION = "auto"  # a method's default (`harness.methods.Numerics`): `resolve_attention` picks one
DRAFT_SLOTS = 75  # cache slots past the prompt: the action and the largest draft tree or candidate set


# VLAConfig's fields that set how, not what, it computes
NUMERICS = ("dtype", "matmul_precision", "unroll", "attention", "patchify")


@dataclasses.dataclass(frozen=True)
class VLAConfig:
    image_size: int = 64  # of each (square) view
    n_views: int = 1  # views tiled left to right in the image (envs.camera: agent view, wrist)
    patch_size: int = 8
    vision_layers: int = 2
    text_len: int = TEXT_LEN
    text_vocab: int = TEXT_VOCAB  # instruction ids [0, text_vocab), PAD_ID = 0
    proprio_dim: int = 8
    d_model: int = 256
    n_layers: int = 8
    n_heads: int = 8
    mlp_dim: int = 688
    cache_slots: int = 0  # 0: prompt_len + DRAFT_SLOTS (7 actions + the largest draft tree, with room to spare)
    rope_base: float = 10000.0
    dtype: str = "float32"  # compute / cache dtype ("bfloat16" for speed)
    # Precision of float32 matrix products (MATMUL_PRECISIONS); in bfloat16 only
    # "bf16_invariant" changes anything (batch-invariant kernels, `invariant_products`).
    matmul_precision: str = "float32"
    # Inference passes with the decoder layers, and AR's token loop, unrolled (see `VLA`).
    unroll: bool = False
    # How a pass without a cache (the prefill, with or without a block) attends in the decoder
    # (ATTENTIONS): "xla", products and softmax as XLA fuses them; "cudnn", cuDNN's fused
    # (flash) attention, on a GPU in bfloat16 or float16 only (`check_attention`). At a 7B
    # scale's 277-token prompt the fused kernel saves what three kernels per layer and the
    # strided read of their output cost (docs/scale.md).
    attention: str = "xla"
    # How the vision tower cuts the image into patch embeddings (PATCHIFIES), one function with
    # the same parameters: "conv", a convolution whose stride is its kernel (cuDNN's on a GPU);
    # "dense", the same sums as one matrix product over the patches (`Patchify`).
    patchify: str = "conv"
    # Larger architectures (`heisd_jax.scale` expands a trained target into them); 0 means
    # "as the fields above", which is how every trained checkpoint is built.
    vocab: int = 0  # 0: text_vocab + 256; more: unused ids after the action ids
    image_tokens: int = 0  # 0: n_patches; more: pad tokens before the patches, which no token attends to
    vision_width: int = 0  # 0: d_model; else the vision tower's width, projected linearly to d_model
    vision_heads: int = 0  # 0: n_heads
    vision_mlp: int = 0  # 0: mlp_dim
    norm_eps: float = 1e-6  # RMSNorm epsilon of the decoder (and drafter)
    vision_norm_eps: float = 1e-6  # RMSNorm epsilon of the vision tower
    # Decoder weights as one array per layer (params "layer0", "layer1", ...) instead of stacked
    # arrays under a scan ("blocks"): a large model's passes then read each weight in place
    # (slicing a layer out of stacked arrays makes XLA copy it: ~2x a 7B pass).
    per_layer: bool = False

    @property
    def batch_invariant(self) -> bool:
        """Batch-invariant numerics (`invariant_products`; the model's own share: the vision
        softmax in float32, multi-token passes attending at AR's slots)."""
        return self.matmul_precision == "bf16_invariant"

    def architecture(self) -> dict:
        """The fields that fix the function and the parameters' shapes: all but the numerics
        (`NUMERICS`), which a caller may change for one run (a drafter trained for a target
        serves it at any of them)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in NUMERICS}

    @property
    def n_patches(self) -> int:
        return self.n_views * (self.image_size // self.patch_size) ** 2

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """[H, W, 3] of one observation's image: the views side by side."""
        return (self.image_size, self.n_views * self.image_size, 3)

    @property
    def image_pad(self) -> int:
        """Pad tokens ahead of the image patches (a scaled-up prompt's length, not its content)."""
        return self.image_tokens - self.n_patches

    @property
    def prompt_len(self) -> int:
        return self.image_tokens + self.text_len + 1

    @property
    def vocab_size(self) -> int:
        return self.vocab

    @property
    def first_action_id(self) -> int:
        return self.text_vocab

    def __post_init__(self):
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise ValueError(f"matmul_precision {self.matmul_precision!r}: valid are {', '.join(MATMUL_PRECISIONS)}")
        if self.attention not in ATTENTIONS:
            raise ValueError(f"attention {self.attention!r}: valid are {', '.join(ATTENTIONS)}")
        if self.patchify not in PATCHIFIES:
            raise ValueError(f"patchify {self.patchify!r}: valid are {', '.join(PATCHIFIES)}")
        if self.attention == "cudnn" and self.dtype not in FUSED_ATTENTION_DTYPES:
            raise ValueError(f"attention 'cudnn' computes in bfloat16 or float16, not {self.dtype}; "
                             f"valid for {self.dtype}: xla")
        if self.n_views < 1:
            raise ValueError(f"n_views must be >= 1, got {self.n_views}")
        if self.image_size % self.patch_size:
            raise ValueError(f"image_size {self.image_size} is not a multiple of patch_size {self.patch_size}")
        if self.d_model % self.n_heads or (self.d_model // self.n_heads) % 2:
            raise ValueError(f"d_model {self.d_model} must split into {self.n_heads} heads of even size")
        for name, default in (("vocab", self.text_vocab + N_BINS), ("image_tokens", self.n_patches),
                              ("vision_width", self.d_model), ("vision_heads", self.n_heads),
                              ("vision_mlp", self.mlp_dim)):
            if getattr(self, name) == 0:
                object.__setattr__(self, name, default)
        if self.vocab < self.text_vocab + N_BINS:
            raise ValueError(f"vocab {self.vocab} < text_vocab {self.text_vocab} + {N_BINS} action ids")
        if self.image_tokens < self.n_patches:
            raise ValueError(f"image_tokens {self.image_tokens} < the image's {self.n_patches} patches")
        if self.vision_width % self.vision_heads:
            raise ValueError(f"vision_width {self.vision_width} must split into {self.vision_heads} heads")
        if self.cache_slots == 0:
            object.__setattr__(self, "cache_slots", self.prompt_len + DRAFT_SLOTS)
        if self.cache_slots < self.prompt_len + ACTION_DIM:
            raise ValueError(f"cache_slots {self.cache_slots} < prompt {self.prompt_len} + {ACTION_DIM} actions")


# How float32 matrix products run, by name -> the setting of `jax.default_matmul_precision`
# (None: XLA's default). "float32": full float32 on every backend. "default": XLA's choice,
# which on recent NVIDIA GPUs runs some shapes on TF32 tensor cores and others in float32, so
# one state's logits differ between batch sizes. "tf32" and "bf16": one pinned algorithm for
# every product (TF32, or bfloat16 inputs), float32 accumulation: tensor-core speed with the
# same kind of kernel at every shape. "tf32x3", "bf16x3", "bf16x6", "bf16x9": each input split
# into a sum of 2 or 3 such terms and 3, 6 or 9 tensor-core products of them summed, close to
# float32's rounding (arXiv 1904.06376); on an H100 none is both faster than "float32" and
# batch-invariant (BENCHMARKS.md). "tf32_rounded": every product's operands rounded to TF32
# first (`rounded_products`), then TF32 tensor cores on a GPU and float32 elsewhere: the
# products are exact in either, so every kernel forms the same ones, whichever a shape gets.
# "bf16_invariant", in either dtype: every product on bfloat16 operands, float32 accumulation,
# by one fixed-tile kernel, and every sum in a fixed order (`invariant_products`), so a row's
# result does not depend on the batch around it.
_PRECISION_SETTINGS = {"float32": "float32", "default": None, "tf32": "TF32_TF32_F32", "bf16": "BF16_BF16_F32",
                       "tf32x3": "TF32_TF32_F32_X3", "bf16x3": "BF16_BF16_F32_X3", "bf16x6": "BF16_BF16_F32_X6",
                       "bf16x9": "BF16_BF16_F32_X9", "tf32_rounded": "TF32_TF32_F32",
                       "bf16_invariant": None}
MATMUL_PRECISIONS = tuple(_PRECISION_SETTINGS)
_GPU_ONLY = ("tf32", "tf32x3", "bf16x9")  # XLA's CPU backend has no such algorithm


def at_config_precision(fn):
    """Runs fn(params, cfg, ...) with float32 matrix products at cfg.matmul_precision (the
    setting applies while fn is traced, so inside jit too)."""

    @functools.wraps(fn)
    def wrapped(params, cfg: VLAConfig, *args, **kwargs):
        float32 = jnp.dtype(cfg.dtype) == jnp.float32
        setting = _PRECISION_SETTINGS[cfg.matmul_precision] if float32 else None
        on_gpu = jax.default_backend() == "gpu"
        if setting and cfg.matmul_precision in _GPU_ONLY and not on_gpu:
            raise ValueError(f'matmul_precision "{cfg.matmul_precision}" needs a GPU (the backend is '
                             f"{jax.default_backend()}); valid here: "
                             f"{', '.join(p for p in MATMUL_PRECISIONS if p not in _GPU_ONLY)}")
        if cfg.batch_invariant:
            return invariant_products.batch_invariant(fn)(params, cfg, *args, **kwargs)
        rounded = float32 and cfg.matmul_precision == "tf32_rounded"
        if rounded and not on_gpu:
            setting = "float32"  # no TF32 units: the rounded operands' exact products in float32
        with jax.default_matmul_precision(setting) if setting else contextlib.nullcontext():
            return (rounded_products.with_tf32_operands(fn) if rounded else fn)(params, cfg, *args, **kwargs)

    return wrapped


@struct.dataclass
class KVCache:
    k: jnp.ndarray  # [L, B, S, H, Dh]
    v: jnp.ndarray  # [L, B, S, H, Dh]
    key_mask: jnp.ndarray  # [B, S] bool: slot holds a token later queries may attend to
    length: jnp.ndarray  # [B] int32: committed tokens (next write slot; also next position)


@struct.dataclass
class Block:
    """Keys/values of the T tokens of the last pass, not in the cache: [L, B, T, H, Dh]."""
    k: jnp.ndarray
    v: jnp.ndarray


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_observation(cfg: VLAConfig, obs: Observation) -> int:
    """Checks a batch of observations against the model before it meets the model, so a bad
    input fails here with the field, its shape and the expected shape, not deep inside Flax.
    Shapes and dtypes are always checked (free, even at trace time); values (finite proprio,
    instruction ids in [0, text_vocab)) only when the arrays are concrete, since a tracer's
    values are unknown. Returns the batch size B. Raises ValueError (TypeError for a value
    that is not an `Observation`)."""
    if not isinstance(obs, Observation):
        raise TypeError(f"obs must be a heisd_jax.observation.Observation, got {type(obs).__name__}")
    expected = {"image": ("B", *cfg.image_shape), "instruction": ("B", cfg.text_len), "proprio": ("B", cfg.proprio_dim)}
    shapes = {}
    for name, want in expected.items():
        x = getattr(obs, name)
        shape = tuple(getattr(x, "shape", ()))
        want_s = "[" + ", ".join(map(str, want)) + "]"
        if len(shape) != len(want) or shape[1:] != want[1:]:
            hint = ""
            if name == "image" and len(shape) == 4 and shape[1] == 3 and shape[2:] == cfg.image_shape[:2]:
                hint = " (channels first? images are channels last: [B, H, W, 3])"
            raise ValueError(f"observation.{name} has shape {list(shape)}, expected {want_s}{hint}")
        shapes[name] = shape
    batch = {name: shape[0] for name, shape in shapes.items()}
    if len(set(batch.values())) > 1:
        raise ValueError("observation fields disagree on the batch size B: "
                         + ", ".join(f"{n} {list(shapes[n])}" for n in expected))
    if obs.image.dtype != jnp.uint8:
        raise ValueError(f"observation.image has dtype {obs.image.dtype}, expected uint8 (pixels 0..255)")
    if not jnp.issubdtype(obs.instruction.dtype, jnp.integer):
        raise ValueError(f"observation.instruction has dtype {obs.instruction.dtype}, expected int32 token ids")
    if not jnp.issubdtype(obs.proprio.dtype, jnp.floating):
        raise ValueError(f"observation.proprio has dtype {obs.proprio.dtype}, expected float32")
    if _is_concrete(obs.proprio):
        proprio = np.asarray(obs.proprio)
        bad = ~np.isfinite(proprio)
        if bad.any():
            rows = np.flatnonzero(bad.any(-1))
            raise ValueError(f"observation.proprio has non-finite values (NaN/inf) in rows {rows[:8].tolist()}"
                             f"{' ...' if len(rows) > 8 else ''} of shape {list(proprio.shape)}")
    if _is_concrete(obs.instruction):
        ids = np.asarray(obs.instruction)
        if ids.size and (ids.min() < 0 or ids.max() >= cfg.text_vocab):
            raise ValueError(f"observation.instruction has token ids in [{ids.min()}, {ids.max()}], "
                             f"expected [0, {cfg.text_vocab}) (text_vocab)")
    return batch["image"]


def observation_valid(cfg: VLAConfig, obs: Observation) -> jnp.ndarray:
    """[B] bool, jit-safe: the row's proprio is finite and its instruction ids lie in
    [0, text_vocab). The value checks of `check_observation`, which cannot raise under jit:
    a row that fails them decodes to a meaningless action (NaN logits argmax to bin 0, a
    full-speed move on every axis), so `mark_invalid` makes its result explicit instead."""
    finite = jnp.isfinite(obs.proprio).all(-1)
    ids_ok = ((obs.instruction >= 0) & (obs.instruction < cfg.text_vocab)).all(-1)
    return finite & ids_ok


def mark_invalid(cfg: VLAConfig, obs: Observation, tokens: jnp.ndarray, stats: dict) -> tuple[jnp.ndarray, dict]:
    """A decoding's (tokens [B, 7], per-row stats) with the rows of an invalid observation
    (`observation_valid`) made explicit: their tokens are `tokenizer.INVALID_ID` (which
    `ActionTokenizer.to_actions` turns into the zero action) and `stats["invalid"]` is 1.0 there,
    0.0 elsewhere (an evaluator sums it per episode). Valid rows are unchanged."""
    valid = observation_valid(cfg, obs)
    return (jnp.where(valid[:, None], tokens, INVALID_ID),
            {**stats, "invalid": (~valid).astype(jnp.float32)})


def committed_slots(cache: KVCache) -> jnp.ndarray:
    """[B, S] bool: the slots a query may attend to, those with their key mask on and below
    the row's length (a slot past the length holds a discarded draft's leftovers)."""
    slots = jnp.arange(cache.key_mask.shape[1])
    return cache.key_mask & (slots[None] < cache.length[:, None])


def init_cache(cfg: VLAConfig, batch: int) -> KVCache:
    shape = (cfg.n_layers, batch, cfg.cache_slots, cfg.n_heads, cfg.d_model // cfg.n_heads)
    return KVCache(k=jnp.zeros(shape, cfg.dtype), v=jnp.zeros(shape, cfg.dtype),
                   key_mask=jnp.zeros((batch, cfg.cache_slots), bool), length=jnp.zeros((batch,), jnp.int32))


def rotary_angles(cfg: VLAConfig, positions: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(cos, sin) [B, T, 1, Dh/2] float32 of tokens at positions [B, T], computed once per
    pass and shared by every layer. Rotary positions count real tokens only: a scaled-up
    prompt's pads sit at slots 0..image_pad-1."""
    if cfg.image_pad:
        positions = jnp.maximum(positions - cfg.image_pad, 0)
    half = cfg.d_model // cfg.n_heads // 2
    freq = 1.0 / (cfg.rope_base ** (jnp.arange(half, dtype=jnp.float32) / half))
    ang = positions[..., None].astype(jnp.float32) * freq  # [B, T, half]
    return jnp.cos(ang)[:, :, None], jnp.sin(ang)[:, :, None]


def rope(x: jnp.ndarray, rotary: tuple[jnp.ndarray, jnp.ndarray]) -> jnp.ndarray:
    """Rotary embedding of x [B, T, H, Dh] by `rotary_angles`' (cos, sin)."""
    cos, sin = rotary
    half = x.shape[-1] // 2
    x1, x2 = x[..., :half].astype(jnp.float32), x[..., half:].astype(jnp.float32)
    return jnp.concatenate([x1 * cos - x2 * sin, x1 * sin + x2 * cos], -1).astype(x.dtype)


class SwiGLU(nn.Module):
    hidden: int
    dtype: str

    @nn.compact
    def __call__(self, x):
        g = nn.Dense(self.hidden, use_bias=False, dtype=self.dtype, name="gate")(x)
        u = nn.Dense(self.hidden, use_bias=False, dtype=self.dtype, name="up")(x)
        return nn.Dense(x.shape[-1], use_bias=False, dtype=self.dtype, name="down")(nn.silu(g) * u)


class DecoderBlock(nn.Module):
    """Pre-norm causal block. Attends to a read-only cache and to its own tokens; returns
    the tokens' keys/values (the caller decides which to keep)."""

    cfg: VLAConfig

    @nn.compact
    def __call__(self, x, layer_k, layer_v, rotary, cache_mask, block_mask, ancestor_slots=None):
        # x [B, T, D]; layer_k/v [B, S, H, Dh] or None (no cache); rotary: `rotary_angles`;
        # cache_mask [B, T, S] (which cache slots each token sees; None without a cache);
        # block_mask [B, T, T] (which of the block's tokens each sees, itself included);
        # ancestor_slots [B, T, S] or None: `ancestor_slots`, for `_attend_at_ar_slots` (without a
        # cache: of the block after the prompt, the pass's last T' tokens).
        cfg = self.cfg
        b, t, d = x.shape
        hd = d // cfg.n_heads
        h = nn.RMSNorm(epsilon=cfg.norm_eps, dtype=cfg.dtype, name="attn_norm")(x)
        qkv = nn.Dense(3 * d, use_bias=False, dtype=cfg.dtype, name="qkv")(h).reshape(b, t, 3, cfg.n_heads, hd)
        q, k, v = rope(qkv[:, :, 0], rotary), rope(qkv[:, :, 1], rotary), qkv[:, :, 2]
        k, v = k.astype(cfg.dtype), v.astype(cfg.dtype)
        scale = 1.0 / jnp.sqrt(hd)
        logits = jnp.einsum("bthd,bshd->bhts", q, k).astype(jnp.float32)
        if t == 1:
            # One token's logit on itself is a [H, Dh] product, which XLA lowers to a reduction;
            # fused into the softmax's concatenation below it runs as one serial loop per head
            # (at 7B on an H100, 25 us a layer: an eighth of a cached token's pass). Kept apart,
            # it is one parallel reduction.
            logits = jax.lax.optimization_barrier(logits)
        logits = logits * scale
        logits = jnp.where(block_mask[:, None], logits, NEG_INF)
        if layer_k is None and ancestor_slots is not None:
            # The prompt attends within itself; a block after it, as AR's passes over the
            # prefill's cache (the invariant numerics' products and sums give the prompt's rows
            # the same bits computed apart).
            p, slots = t - ancestor_slots.shape[1], ancestor_slots.shape[2]
            attn = jax.nn.softmax(logits[:, :, :p, :p], -1).astype(cfg.dtype)
            pad = ((0, 0), (0, slots - p), (0, 0), (0, 0))
            seen = jnp.pad(block_mask[:, p:, :p], ((0, 0), (0, 0), (0, slots - p)))
            block = _attend_at_ar_slots(q[:, p:], k[:, p:], v[:, p:], jnp.pad(k[:, :p], pad), jnp.pad(v[:, :p], pad),
                                        seen, ancestor_slots, scale, cfg.dtype)
            out = jnp.concatenate([jnp.einsum("bhts,bshd->bthd", attn, v[:, :p]), block], 1)
        elif layer_k is None and cfg.attention == "cudnn":
            out = fused_attention(q, k, v, block_mask, hd)
        elif layer_k is None:
            attn = jax.nn.softmax(logits, -1).astype(cfg.dtype)
            out = jnp.einsum("bhts,bshd->bthd", attn, v)
        elif ancestor_slots is not None:
            out = _attend_at_ar_slots(q, k, v, layer_k, layer_v, cache_mask, ancestor_slots, scale, cfg.dtype)
        else:  # one softmax over [cache slots, block tokens]
            cache_logits = jnp.einsum("bthd,bshd->bhts", q, layer_k).astype(jnp.float32) * scale
            cache_logits = jnp.where(cache_mask[:, None], cache_logits, NEG_INF)
            attn = jax.nn.softmax(jnp.concatenate([cache_logits, logits], -1), -1).astype(cfg.dtype)
            out = (jnp.einsum("bhts,bshd->bthd", attn[..., :-t], layer_v)
                   + jnp.einsum("bhts,bshd->bthd", attn[..., -t:], v))
        x = x + nn.Dense(d, use_bias=False, dtype=cfg.dtype, name="out")(out.reshape(b, t, d))
        x = x + SwiGLU(cfg.mlp_dim, cfg.dtype, name="mlp")(nn.RMSNorm(epsilon=cfg.norm_eps, dtype=cfg.dtype,
                                                                          name="mlp_norm")(x))
        return x, (k, v)


def check_attention(attention: str) -> None:
    """Refuses an attention (`VLAConfig.attention`, or AUTO_ATTENTION) this process's backend cannot run."""
    if attention == "cudnn" and jax.default_backend() != "gpu":
        raise ValueError(f"attention 'cudnn' runs on a GPU, not on {jax.default_backend()}; valid here: "
                         f"{AUTO_ATTENTION}, xla")


def resolve_attention(attention: str, cfg: VLAConfig, backend: str | None = None) -> str:
    """The attention (ATTENTIONS) that `attention` gives model `cfg` on `backend` (None: this
    process's): `attention` itself, or for AUTO_ATTENTION cuDNN's fused attention where it runs and
    pays -- a GPU, a 16-bit dtype, a large model's per-layer decoder (`per_layer`: a
    `heisd_jax.scale` expansion, whose prefill at 7B it makes 1.1x faster, AR 1.03x; docs/scale.md),
    without `bf16_invariant` products (which compute the attention's products themselves) --
    and XLA's elsewhere: on a CPU, in float32, and at a trained target's own small size, where it
    is not measured to pay (in the 7B vision tower's 8 heads it was slower)."""
    if attention != AUTO_ATTENTION:
        return attention
    fused = ((backend or jax.default_backend()) == "gpu" and cfg.dtype in FUSED_ATTENTION_DTYPES
             and cfg.per_layer and not cfg.batch_invariant)
    return "cudnn" if fused else "xla"


def fused_attention(q, k, v, mask, head_dim: int) -> jnp.ndarray:
    """cuDNN's fused attention of q [B, T, H, Dh] over k, v [B, S, H, Dh] where mask [B, T, S]
    holds: [B, T, H, Dh], laid out row by row, so the output projection after it reads it as
    a plain matrix. A masked key gets the additive bias NEG_INF (finite: a query that sees no
    key, a pad token's, gets a finite average, as under XLA's softmax, not NaN)."""
    check_attention("cudnn")
    bias = jnp.where(mask[:, None], 0.0, NEG_INF).astype(q.dtype)
    return jax.nn.dot_product_attention(q, k, v, bias=bias, scale=float(1.0 / np.sqrt(head_dim)),
                                        implementation="cudnn")


def ancestor_slots(positions: jnp.ndarray, block_mask: jnp.ndarray, slots: int) -> jnp.ndarray:
    """[B, T, S] int: for each block token and cache slot, the block token that AR would find at
    that slot when decoding it (one of its ancestors: a committed token's slot is its position),
    or -1 where it finds the cache's own entry. positions [B, T]; block_mask [B, T, T]."""
    t = positions.shape[1]
    ancestor = block_mask & ~jnp.eye(t, dtype=bool)[None]  # [B, T(query), T(block token)]
    at = ancestor[:, :, None, :] & (positions[:, None, None, :] == jnp.arange(slots)[None, None, :, None])
    return jnp.where(at.any(-1), jnp.argmax(at, -1), -1).astype(jnp.int32)


def _attend_at_ar_slots(q, k, v, layer_k, layer_v, cache_mask, src, scale, dtype):
    """Attention of a block of T tokens laid out as AR lays out each one's single-token pass:
    a softmax over [the S cache slots, itself], where an ancestor's score and value stand at
    the slot AR's cache holds it in, then weights times values summed over the slots, plus its
    own. With every product and sum in one order per element whatever its shape
    (`invariant_products`), each token of a tree then gets the bits AR's pass gives it, so
    strict verification is token-identical to AR in bfloat16 too. Costs a per-token copy of the
    layer's values ([B, T, S, H, Dh]); used under `matmul_precision="bf16_invariant"` by passes of
    more than one token against a cache, and by a block after the prompt in the prefill (its
    "cache" then the pass's own prompt keys and values, as the prefill would store them).
    q, k, v [B, T, H, Dh]; layer_k/v [B, S, H, Dh]; cache_mask [B, T, S]; src [B, T, S]."""
    from_block = src >= 0  # [B, T, S]
    at = jnp.maximum(src, 0)
    cache_logits = jnp.einsum("bthd,bshd->bhts", q, layer_k).astype(jnp.float32)
    block_logits = jnp.einsum("bthd,bshd->bhts", q, k).astype(jnp.float32)  # [B, H, T, T]
    ancestors = jnp.take_along_axis(block_logits, jnp.broadcast_to(at[:, None], cache_logits.shape), -1)
    logits = jnp.where(from_block[:, None], ancestors, cache_logits) * scale
    logits = jnp.where((cache_mask | from_block)[:, None], logits, NEG_INF)
    own = jnp.diagonal(block_logits, axis1=-2, axis2=-1)[..., None] * scale  # [B, H, T, 1]
    attn = jax.nn.softmax(jnp.concatenate([logits, own], -1), -1).astype(dtype)
    rows = jnp.arange(v.shape[0])[:, None, None]
    values = jnp.where(from_block[..., None, None], v[rows, at], layer_v[:, None])  # [B, T, S, H, Dh]
    return (jnp.einsum("bhts,btshd->bthd", attn[..., :-1], values)
            + jnp.einsum("bhtk,btkhd->bthd", attn[..., -1:], v[:, :, None]))


class Patchify(nn.Module):
    """Non-overlapping p x p patches of [B, H, W, C] -> [B, H/p, W/p, features]: the convolution
    whose stride is its kernel, computed as one matrix product of the patches (flattened in the
    kernel's (row, column, channel) order) and the kernel reshaped to [p*p*C, features], plus the
    bias. The parameters are `nn.Conv`'s (names, shapes, initialisers), so a checkpoint serves
    either form. Why a product: on a GPU XLA runs a convolution as a cuDNN call that a CUDA graph
    (a command buffer) cannot hold, so every conditional with the prefill in a branch -- a decode
    step's skip and budget choices -- is then run from the host, which reads its predicate and
    launches the graphs after it; a product is a GEMM the graph holds."""

    features: int
    patch: int
    dtype: str

    @nn.compact
    def __call__(self, x):
        p, c = self.patch, x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (p, p, c, self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        b, h, w, _ = x.shape
        patches = x.reshape(b, h // p, p, w // p, p, c).transpose(0, 1, 3, 2, 4, 5).reshape(b, h // p, w // p, -1)
        return patches @ kernel.reshape(p * p * c, self.features) + bias


class VisionEncoder(nn.Module):
    """Patchify + a small bidirectional ViT: [B, H, W, 3] uint8 -> [B, image_tokens, D]. Tiled
    views are patchified alike; the learned position embedding tells them apart. A scaled-up
    tower (`cfg.image_pad`) puts pad tokens ahead of the patches, which no token attends to,
    and a tower wider than the decoder ends in a linear projection to its width."""

    cfg: VLAConfig

    @nn.compact
    def __call__(self, image):
        cfg = self.cfg
        w, eps = cfg.vision_width, cfg.vision_norm_eps
        x = image.astype(jnp.float32) / 127.5 - 1.0
        if cfg.patchify == "dense":
            x = Patchify(w, cfg.patch_size, cfg.dtype, name="patchify")(x)
        else:
            x = nn.Conv(w, (cfg.patch_size, cfg.patch_size), strides=cfg.patch_size, dtype=cfg.dtype, name="patchify")(x)
        b = x.shape[0]
        x = x.reshape(b, -1, w)
        mask = None
        if cfg.image_pad:
            x = jnp.concatenate([jnp.zeros((b, cfg.image_pad, w), x.dtype), x], 1)
            mask = (jnp.arange(cfg.image_tokens) >= cfg.image_pad)[None, None, None, :]  # keys: the patches only
        x = x + self.param("pos", nn.initializers.normal(0.02), (1, cfg.image_tokens, w)).astype(x.dtype)
        for i in range(cfg.vision_layers):
            h = nn.RMSNorm(epsilon=eps, dtype=cfg.dtype, name=f"norm{i}")(x)
            # Batch-invariant numerics take this softmax in float32, as the decoder's is: a bf16
            # softmax's intermediates round as XLA fuses them, which differs per batch size.
            x = x + nn.MultiHeadDotProductAttention(cfg.vision_heads, dtype=cfg.dtype, name=f"attn{i}",
                                                    force_fp32_for_softmax=cfg.batch_invariant)(h, h, mask=mask)
            x = x + SwiGLU(cfg.vision_mlp, cfg.dtype, name=f"mlp{i}")(
                nn.RMSNorm(epsilon=eps, dtype=cfg.dtype, name=f"mlp_norm{i}")(x))
        x = nn.RMSNorm(epsilon=eps, dtype=cfg.dtype, name="out_norm")(x)
        if w != cfg.d_model:
            x = nn.Dense(cfg.d_model, use_bias=False, dtype=cfg.dtype, name="proj")(x)
        return x


class VLA(nn.Module):
    """`training`: the decoder layers unrolled instead of scanned, for the teacher-forced pass
    a training step differentiates (the scan's backward stores and copies every layer's
    residuals; docs/target.md has the step times). The same function; inference passes keep
    the scan, which compiles faster, unless `cfg.unroll`: on a GPU XLA runs a scan's every
    iteration as its own launch from the host, which bounds a batch-1 decode (BENCHMARKS.md,
    the host-loop profile), while an unrolled pass is one straight-line program: cheaper
    inside a compiled loop, dearer per call from Python (its CUDA graph is updated on
    every call)."""
    cfg: VLAConfig
    training: bool = False

    def setup(self):
        cfg = self.cfg
        self.vision = VisionEncoder(cfg)
        self.embed = nn.Embed(cfg.vocab_size, cfg.d_model, dtype=cfg.dtype, embedding_init=nn.initializers.normal(0.02))
        self.proprio_proj = nn.Dense(cfg.d_model, dtype=cfg.dtype)
        if cfg.per_layer:
            self.layers = [DecoderBlock(cfg, name=f"layer{i}") for i in range(cfg.n_layers)]
        else:
            self.blocks = nn.scan(
                DecoderBlock, variable_axes={"params": 0}, split_rngs={"params": True},
                in_axes=(0, 0, nn.broadcast, nn.broadcast, nn.broadcast, nn.broadcast), length=cfg.n_layers,
                unroll=cfg.n_layers if self.training or cfg.unroll else 1,
            )(cfg)
        self.final_norm = nn.RMSNorm(epsilon=cfg.norm_eps, dtype=cfg.dtype)
        self.head = nn.Dense(cfg.vocab_size, use_bias=False, dtype=cfg.dtype)

    def prompt_embeddings(self, obs: Observation) -> jnp.ndarray:
        """[B, prompt_len, D]: visual tokens, instruction tokens, proprio token."""
        vis = self.vision(obs.image)
        txt = self.embed(obs.instruction)
        prop = self.proprio_proj(obs.proprio.astype(jnp.float32))[:, None]
        return jnp.concatenate([vis, txt, prop], 1)

    def embed_tokens(self, tokens):
        return self.embed(tokens)

    def run(self, x, cache: KVCache | None, positions, cache_mask, block_mask, logits_from: int = 0):
        """Decoder over embeddings x [B, T, D] against a read-only cache (None: none);
        returns hidden [B, T, D], logits [B, T - logits_from, V] (of the tokens from
        `logits_from` on: a prefill needs only its last prompt token's) and the tokens'
        keys/values [L, B, T, H, Dh]."""
        ck, cv = (None, None) if cache is None else (cache.k, cache.v)
        rotary = rotary_angles(self.cfg, positions)
        # Under invariant numerics a pass of several tokens against a cache, or of a block after
        # the prompt, attends as AR's single-token passes would (`_attend_at_ar_slots`).
        slots, cfg = None, self.cfg
        if cfg.batch_invariant:
            p = cfg.prompt_len
            if cache is not None and x.shape[1] > 1:
                slots = ancestor_slots(positions, block_mask, cache.k.shape[2])
            elif cache is None and x.shape[1] > p:
                slots = ancestor_slots(positions[:, p:], block_mask[:, p:, p:], cfg.cache_slots)
        if cfg.per_layer:
            kv = []
            for i, layer in enumerate(self.layers):
                x, out = layer(x, None if ck is None else ck[i], None if cv is None else cv[i], rotary, cache_mask,
                               block_mask, slots)
                kv.append(out)
            k, v = jnp.stack([a for a, _ in kv]), jnp.stack([b for _, b in kv])
        else:
            x, (k, v) = self.blocks(x, ck, cv, rotary, cache_mask, block_mask, slots)
        hidden = self.final_norm(x)
        return hidden, self.head(hidden[:, logits_from:]).astype(jnp.float32), (k, v)

    def __call__(self, obs: Observation, tokens, logits_from: int = 0):
        """Initialisation / teacher forcing entry: prompt + tokens [B, T] -> logits of the
        positions from `logits_from` on [B, P + T - logits_from, V], hidden [B, P + T, D]."""
        x = jnp.concatenate([self.prompt_embeddings(obs), self.embed_tokens(tokens)], 1)
        n = x.shape[1]
        key_ok = jnp.concatenate([prompt_key_mask(self.cfg, obs.instruction), jnp.ones(tokens.shape, bool)], 1)
        mask = causal_mask(n, n)[None] & key_ok[:, None, :]
        positions = jnp.broadcast_to(jnp.arange(n), (x.shape[0], n))
        hidden, logits, _ = self.run(x, None, positions, None, mask, logits_from)
        return logits, hidden


def swiglu_width(d_model: int) -> int:
    """The MLP width a trained target of width `d_model` gets (`train`): SwiGLU's 8/3 of the
    width (its three matrices then hold what a 4x two-matrix MLP holds), a multiple of 8."""
    return int(d_model * 8 / 3 // 8 * 8)


def pad_to(mask, slots):
    """[B, T] -> [B, slots], padded with False."""
    return jnp.pad(mask, ((0, 0), (0, slots - mask.shape[1])))


def causal_mask(t: int, slots: int) -> jnp.ndarray:
    """[T, S]: query i may see slots 0..i (queries written at slots 0..T-1)."""
    return jnp.arange(slots)[None, :] <= jnp.arange(t)[:, None]


def prompt_key_mask(cfg: VLAConfig, instruction: jnp.ndarray) -> jnp.ndarray:
    """[B, prompt_len] bool: prompt slots that hold real tokens (instruction padding is off)."""
    b = instruction.shape[0]
    text_ok = instruction != PAD_ID
    return jnp.concatenate([jnp.zeros((b, cfg.image_pad), bool), jnp.ones((b, cfg.n_patches), bool), text_ok,
                            jnp.ones((b, 1), bool)], 1)


def init_params(cfg: VLAConfig, key: jax.Array) -> dict:
    obs = Observation(image=jnp.zeros((1, *cfg.image_shape), jnp.uint8),
                      instruction=jnp.zeros((1, cfg.text_len), jnp.int32), proprio=jnp.zeros((1, cfg.proprio_dim)))
    return VLA(cfg).init(key, obs, jnp.zeros((1, ACTION_DIM), jnp.int32))["params"]


@at_config_precision
def forward(params, cfg: VLAConfig, obs: Observation, tokens: jnp.ndarray, training: bool = False,
            logits_from: int = 0):
    """Teacher-forced pass over prompt + tokens (no cache): logits [B, P+T-logits_from, V] (of
    the positions from `logits_from` on), hidden [B, P+T, D]. `training`: the variant a
    training step differentiates fastest (`VLA.training`)."""
    return VLA(cfg, training=training).apply({"params": params}, obs, tokens, logits_from)


def prefill(params, cfg: VLAConfig, obs: Observation):
    """One pass over the prompt into a fresh cache. Returns logits and hidden of the last
    prompt position ([B, V], [B, D]) and the cache (length = prompt_len)."""
    logits, hidden, _, cache = prefill_features(params, cfg, obs)
    return logits, hidden[:, -1], cache


def prefill_features(params, cfg: VLAConfig, obs: Observation):
    """Like `prefill`, also returning what a feature-level drafter reads: the last-layer
    hidden states of every prompt position [B, P, D] and the prompt's input embeddings
    [B, P, D]. Returns (last logits [B, V], hidden [B, P, D], embeddings, cache)."""
    logits, hidden, x, cache, _ = _prefill(params, cfg, obs, None)
    return logits[:, 0], hidden, x, cache


def prefill_with_block(params, cfg: VLAConfig, obs: Observation, tokens: jnp.ndarray, depth: jnp.ndarray,
                       intra: jnp.ndarray):
    """The prompt and a block of T draft tokens [B, T] in ONE pass (verification fused into
    the prefill). The block is laid out as `cached_pass` lays it out after a prefill: depth [B, T]
    = position offset from the prompt's end, intra [B, T, T] = which block tokens each may
    attend to (besides the whole prompt). Returns (last prompt logits [B, V], prompt hidden
    [B, P, D], prompt embeddings, block logits [B, T, V], block hidden [B, T, D], cache,
    block keys/values); the cache holds the prompt (length P), and `commit(cache, block,
    ...)` keeps an accepted path exactly as after `cached_pass`."""
    logits, hidden, x, cache, blk = _prefill(params, cfg, obs, (tokens, depth, intra))
    p = cfg.prompt_len
    return logits[:, 0], hidden[:, :p], x, logits[:, 1:], hidden[:, p:], cache, blk


@at_config_precision
def _prefill(params, cfg: VLAConfig, obs: Observation, block):
    model = VLA(cfg)
    b = obs.image.shape[0]
    p = cfg.prompt_len
    key_ok = prompt_key_mask(cfg, obs.instruction)
    mask = causal_mask(p, p)[None] & key_ok[:, None, :]
    positions = jnp.broadcast_to(jnp.arange(p), (b, p))
    if block is not None:
        tokens, depth, intra = block
        t = tokens.shape[1]
        mask = jnp.concatenate([jnp.pad(mask, ((0, 0), (0, 0), (0, t))),
                                jnp.concatenate([jnp.broadcast_to(key_ok[:, None, :], (b, t, p)), intra], 2)], 1)
        positions = jnp.concatenate([positions, p + depth], 1)

    def fn(m):
        x = m.prompt_embeddings(obs)
        full = x if block is None else jnp.concatenate([x, m.embed_tokens(block[0]).astype(x.dtype)], 1)
        return x, m.run(full, None, positions, None, mask, logits_from=p - 1)

    # logits [B, 1 + T, V]: the last prompt token's, then the block's
    x, (hidden, logits, (k, v)) = nn.apply(fn, model)({"params": params})
    pad = ((0, 0), (0, 0), (0, cfg.cache_slots - p), (0, 0), (0, 0))
    cache = KVCache(k=jnp.pad(k[:, :, :p], pad), v=jnp.pad(v[:, :, :p], pad), key_mask=pad_to(key_ok, cfg.cache_slots),
                    length=jnp.full((b,), p, jnp.int32))
    return logits, hidden, x, cache, Block(k=k[:, :, p:], v=v[:, :, p:])


@at_config_precision
def cached_pass(params, cfg: VLAConfig, cache: KVCache, tokens: jnp.ndarray, depth: jnp.ndarray, intra: jnp.ndarray):
    """T tokens [B, T] against the cache (which is not changed).

    depth [B, T]: each token's position offset from the cache length (AR: 0; tree: node
    depth); intra [B, T, T] bool: which of the T new tokens each may attend to (AR: causal;
    tree: ancestors and itself). Returns logits [B, T, V], hidden [B, T, D] and the tokens'
    keys/values (`Block`), which `commit` writes into the cache.
    """
    model = VLA(cfg)
    b, t = tokens.shape
    committed = committed_slots(cache)  # [B, S]
    positions = cache.length[:, None] + depth

    def fn(m):
        return m.run(m.embed_tokens(tokens), cache, positions, jnp.broadcast_to(committed[:, None], (b, t, cfg.cache_slots)),
                     intra)

    hidden, logits, (k, v) = nn.apply(fn, model)({"params": params})
    return logits, hidden, Block(k=k, v=v)


def select_cache(rows: jnp.ndarray, new: KVCache, old: KVCache) -> KVCache:
    """Per row: `new` where rows [B] holds, else `old`. Only `key_mask` and `length` are
    selected; keys/values are `new`'s for every row. That is exact for caches that differ
    only at and after the shorter one's length (what `commit` and the drafter write), where
    the other's key mask hides them; selecting the whole cache would cost a full copy of it
    (batch 1,024: ~3 ms on an H200)."""
    pick = lambda n, o: jnp.where(rows.reshape((-1,) + (1,) * (n.ndim - 1)), n, o)  # noqa: E731
    return KVCache(k=new.k, v=new.v, key_mask=pick(new.key_mask, old.key_mask), length=pick(new.length, old.length))


def commit(cache: KVCache, block: Block, src: jnp.ndarray, n: jnp.ndarray) -> KVCache:
    """Keeps n[b] of the block's tokens: the ones at block offsets src[b, :n[b]] go to slots
    length..length+n-1 (in that order); the rest of the block is dropped. One scatter of
    the kept keys/values into the cache (in place when the old cache is not used again).
    src [B, K] int (block offsets, K static), n [B] int <= K."""
    b, kk = src.shape
    rows = jnp.broadcast_to(jnp.arange(b)[:, None], (b, kk))
    j = jnp.arange(kk)[None]
    dst = jnp.where(j < n[:, None], cache.length[:, None] + j, cache.key_mask.shape[1])  # out of range: dropped
    take = lambda x: x[:, rows, src]  # noqa: E731  [L, B, K, H, Dh]
    k = cache.k.at[:, rows, dst].set(take(block.k), mode="drop")
    v = cache.v.at[:, rows, dst].set(take(block.v), mode="drop")
    slots = jnp.arange(cache.key_mask.shape[1])
    new_len = cache.length + n
    key_mask = committed_slots(cache) | ((slots[None] >= cache.length[:, None]) & (slots[None] < new_len[:, None]))
    return KVCache(k=k, v=v, key_mask=key_mask, length=new_len.astype(jnp.int32))


@at_config_precision
def prompt_embeddings(params, cfg: VLAConfig, obs: Observation) -> jnp.ndarray:
    """The prompt's input embeddings [B, P, D] (vision encoder, text and proprio tokens)."""
    return nn.apply(lambda m: m.prompt_embeddings(obs), VLA(cfg))({"params": params})


def embed_tokens(params, tokens: jnp.ndarray) -> jnp.ndarray:
    """The target's token embeddings (a drafter reuses them, frozen)."""
    return params["embed"]["embedding"][tokens]


@at_config_precision
def action_head(params, cfg: VLAConfig, hidden: jnp.ndarray) -> jnp.ndarray:
    """The target's output head restricted to the 256 action ids: hidden [..., D] -> [..., 256]."""
    kernel = params["head"]["kernel"][:, cfg.first_action_id:cfg.first_action_id + N_BINS]
    return (hidden @ kernel.astype(hidden.dtype)).astype(jnp.float32)


def action_logits(cfg: VLAConfig, logits: jnp.ndarray) -> jnp.ndarray:
    """Restricts logits [..., V] to the 256 action ids: [..., 256] (index = bin)."""
    return logits[..., cfg.first_action_id:cfg.first_action_id + N_BINS]
