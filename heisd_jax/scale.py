"""Function-preserving expansion of a trained target VLA, and of its drafter, into a larger
architecture: the expanded network chooses the trained target's tokens, while each of its
passes costs what a pass of the larger model costs (e.g. OpenVLA-7B's Llama-2 backbone).

The construction (docs/scale.md says why each step is exact):
- residual width d -> D: every vector is zero-padded; every matrix that writes the residual
  stream writes zeros into the extra dims, so they stay zero; RMSNorm's mean of squares then
  shrinks by d/D, which the gain (x sqrt(d/D)) and epsilon (x d/D) absorb;
- heads h -> H, head size hd -> hd': the trained heads keep their index; their queries and
  keys are spread over the wider head so each rotary pair keeps its frequency (pair i of hd
  goes to pair i * hd'/hd), with the query scaled by sqrt(hd'/hd) against the wider head's
  1/sqrt(hd') (bit-exact where hd'/hd is a power of 4); extra heads and extra head dims are
  read by zero rows of the output projection;
- MLP units m -> M: extra units have zero rows in the down projection;
- layers l -> L: the trained layers first, then layers whose attention output and MLP down
  projections are zero (identity on the residual stream, full cost);
- vocabulary: unused ids after the action ids (their logits are computed, never read);
- image tokens: pad tokens ahead of the patches that no token attends to (masked keys in the
  vision tower and the decoder), and rotary positions that count real tokens only;
- vision tower: widened, deepened and given more heads the same way, then a linear
  projection to the decoder's width (the identity on the trained dims).
Entries whose value cannot matter (read only by zero rows, or reading only zero dims) are
filled with N(0, 0.02) noise, so every product is a real product of a real-sized model.

`expand_target(params, cfg, name)` and `expand_drafter(dparams, cfg, name)` build the
weights on the default device, leaf by leaf, from the trained checkpoint: nothing large is
stored. The expanded decoder keeps one weight array per layer (`VLAConfig.per_layer`). `SCALES` names the architectures; `scaled_config` checks a name against a target.
"""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from heisd_jax import vla

SHIPPED = "shipped"  # the trained target as it is


@dataclasses.dataclass(frozen=True)
class TargetScale:
    """A decoder and vision tower to expand into (a VLAConfig's architecture fields)."""
    d_model: int
    n_layers: int
    n_heads: int
    mlp_dim: int
    vocab: int
    image_tokens: int  # decoder image tokens (the vision tower's tokens)
    vision_width: int
    vision_layers: int
    vision_heads: int
    vision_mlp: int
    about: str = ""


# The vision tower of both scales: ~604M parameters over 256 tokens, OpenVLA's fused
# DINOv2-L + SigLIP-So400m (~600M, 256 patches of a 224 px image) by size and tokens.
_VISION = dict(image_tokens=256, vision_width=1024, vision_layers=36, vision_heads=8, vision_mlp=4096)
SCALES: dict[str, TargetScale] = {
    "llama2-7b": TargetScale(4096, 32, 32, 11008, 32000, **_VISION,
                             about="OpenVLA-7B: Llama-2-7B's decoder (6.74B) and a ~0.6B vision tower"),
    "llama-1b": TargetScale(2048, 16, 16, 5632, 32000, **_VISION,
                            about="a ~1B Llama decoder (0.95B) and the same ~0.6B vision tower"),
}
SCALE_NAMES = (SHIPPED, *SCALES)


def _fields(scale: TargetScale) -> dict:
    return {f.name: getattr(scale, f.name) for f in dataclasses.fields(scale) if f.name != "about"}


def _resolve(name: str | TargetScale) -> TargetScale | None:
    if isinstance(name, TargetScale) or name == SHIPPED:
        return None if name == SHIPPED else name
    if name not in SCALES:
        raise ValueError(f"unknown target scale {name!r}; valid: {', '.join(SCALE_NAMES)}")
    return SCALES[name]


def scaled_config(cfg: vla.VLAConfig, name: str | TargetScale) -> vla.VLAConfig:
    """The config of target `cfg` expanded to scale `name` (`SCALE_NAMES`, or a
    `TargetScale`; "shipped": cfg).
    Raises ValueError naming the valid scales for an unknown name or one that is smaller
    than the target in some dimension, or whose head size is not a multiple of the target's."""
    scale = _resolve(name)
    if scale is None:
        return cfg
    new = _fields(scale)
    small = [f"{k} {v} < {getattr(cfg, k)}" for k, v in new.items() if v < getattr(cfg, k)]
    if small:
        raise ValueError(f"target scale {name!r} is smaller than the target ({'; '.join(small)}); valid: "
                         f"{', '.join(SCALE_NAMES)}")
    for width, heads, old_w, old_h, what in ((new["d_model"], new["n_heads"], cfg.d_model, cfg.n_heads, "decoder"),
                                             (new["vision_width"], new["vision_heads"], cfg.vision_width,
                                              cfg.vision_heads, "vision")):
        if (width // heads) % (old_w // old_h):
            raise ValueError(f"target scale {name!r}: {what} head size {width // heads} is not a multiple of the "
                             f"target's {old_w // old_h}")
    return dataclasses.replace(
        cfg, **new, per_layer=True, cache_slots=cfg.cache_slots - cfg.prompt_len + new["image_tokens"] + cfg.text_len + 1,
        norm_eps=cfg.norm_eps * cfg.d_model / new["d_model"],
        vision_norm_eps=cfg.vision_norm_eps * cfg.vision_width / new["vision_width"])


def device_bytes() -> int | None:
    """Memory of the default device (a GPU's allocator limit; on CPU the host's RAM), if known."""
    dev = jax.devices()[0]
    stats = dev.memory_stats() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"])
    if dev.platform == "cpu" and hasattr(os, "sysconf"):
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return None


def check_fits(cfg: vla.VLAConfig, name: str | TargetScale, dtype: str, share: float = 0.8) -> None:
    """Refuses, before any weight is made, a scale whose target and drafter weights in `dtype`
    would take more than `share` of the default device's memory, naming the scales that fit."""
    limit = device_bytes()
    if limit is None or _resolve(name) is None:
        return

    def need(n):
        c = scaled_config(cfg, n)
        return (sum(n_params(c).values()) + 4 * c.d_model ** 2 + 3 * c.d_model * c.mlp_dim) * jnp.dtype(dtype).itemsize
    if need(name) > share * limit:
        fits = [n for n in SCALE_NAMES if n == SHIPPED or need(n) <= share * limit]
        raise ValueError(f"target scale {name!r} in {dtype} needs {need(name) / 2**30:.1f} GiB of weights, more than "
                         f"{share:.0%} of this {jax.devices()[0].device_kind}'s {limit / 2**30:.1f} GiB; valid here: "
                         f"{', '.join(fits)}")


def n_params(cfg: vla.VLAConfig) -> dict[str, int]:
    """Parameter counts of a target of config cfg: decoder (embeddings, layers, head), vision."""
    shapes = jax.eval_shape(lambda: vla.init_params(cfg, jax.random.PRNGKey(0)))
    sizes = {k: sum(math.prod(x.shape) for x in jax.tree.leaves(v)) for k, v in shapes.items()}
    vision = sizes.pop("vision")
    return {"decoder": sum(sizes.values()), "vision": vision}


class _Filler:
    """N(0, 0.02) noise for entries whose value cannot matter, a fresh key per leaf."""

    def __init__(self, seed: int, dtype):
        self.key, self.dtype = jax.random.PRNGKey(seed), jnp.dtype(dtype)

    def __call__(self, shape) -> jnp.ndarray:
        self.key, k = jax.random.split(self.key)
        return (jax.random.normal(k, shape, jnp.float32) * 0.02).astype(self.dtype)


def _spread(x: jnp.ndarray, index: np.ndarray, size: int) -> jnp.ndarray:
    """x [..., n] -> [..., size]: x's entries at positions `index` [n], zeros elsewhere."""
    return jnp.zeros((*x.shape[:-1], size), x.dtype).at[..., index].set(x)


def _rotary_index(hd: int, new_hd: int) -> np.ndarray:
    """Where each dim of a head of size hd goes in a head of size new_hd so that every rotary
    pair (c, c + hd/2) keeps its frequency: pair c -> pair c * new_hd / hd."""
    half, r = hd // 2, new_hd // hd
    c = np.arange(half)
    return np.concatenate([r * c, new_hd // 2 + r * c])


class _Expander:
    """Builds the expanded parameter trees of one target (or drafter), config old -> new, in
    dtype; `lead` arguments are the leading axes of stacked layers."""

    def __init__(self, old: vla.VLAConfig, new: vla.VLAConfig, dtype, seed: int):
        self.old, self.new, self.fill, self.dtype = old, new, _Filler(seed, dtype), jnp.dtype(dtype)
        self.gain = math.sqrt(old.d_model / new.d_model)
        self.vgain = math.sqrt(old.vision_width / new.vision_width)

    def put(self, old: jnp.ndarray, new_shape, rest_zero: bool = False) -> jnp.ndarray:
        """A leaf of new_shape: old's values in the leading corner, noise (or, with
        `rest_zero`, zeros) elsewhere."""
        out = jnp.zeros(new_shape, self.dtype) if rest_zero else self.fill(new_shape)
        corner = tuple(slice(0, n) for n in old.shape)
        return out.at[corner].set(jnp.asarray(old, jnp.float32).astype(self.dtype))

    def norm(self, g: jnp.ndarray, width: int, gain: float, lead=()) -> jnp.ndarray:
        """An RMSNorm gain [..., w] -> [..., width], trained dims scaled by `gain`."""
        return self.put(jnp.asarray(g, jnp.float32) * gain, (*lead, width))

    # -- attention ------------------------------------------------------------------------
    def qkv(self, k: jnp.ndarray, lead=()) -> jnp.ndarray:
        """The decoder's fused qkv kernel [..., d, 3 d] -> [..., D, 3 D]."""
        o, n = self.old, self.new
        hd, new_hd = o.d_model // o.n_heads, n.d_model // n.n_heads
        k = jnp.asarray(k, jnp.float32).reshape(*lead, o.d_model, 3, o.n_heads, hd)
        rot = _rotary_index(hd, new_hd)
        qk = _spread(k[..., :2, :, :], rot, new_hd) * jnp.asarray([math.sqrt(new_hd / hd), 1.0])[:, None, None]
        out = self.fill((*lead, n.d_model, 3, n.n_heads, new_hd))
        out = out.at[..., :2, :o.n_heads, :].set(0)  # trained heads' q, k: the spread dims alone
        out = out.at[..., :o.d_model, :2, :o.n_heads, :].set(qk.astype(self.dtype))
        out = out.at[..., :o.d_model, 2, :o.n_heads, :hd].set(k[..., 2, :, :].astype(self.dtype))
        return out.reshape(*lead, n.d_model, 3 * n.d_model)

    def attn_out(self, k: jnp.ndarray, lead=()) -> jnp.ndarray:
        """The decoder's attention output kernel [..., d, d] -> [..., D, D] (rows: heads x dims)."""
        o, n = self.old, self.new
        hd, new_hd = o.d_model // o.n_heads, n.d_model // n.n_heads
        k = jnp.asarray(k, jnp.float32).reshape(*lead, o.n_heads, hd, o.d_model)
        out = jnp.zeros((*lead, n.n_heads, new_hd, n.d_model), self.dtype)
        out = out.at[..., :o.n_heads, :hd, :o.d_model].set(k.astype(self.dtype))
        return out.reshape(*lead, n.d_model, n.d_model)

    # -- MLP ------------------------------------------------------------------------------
    def mlp(self, p: dict, width: int, hidden: int, old_width: int, lead=()) -> dict:
        """SwiGLU {gate, up, down} of residual width old_width -> width, units -> hidden."""
        old_down = jnp.asarray(p["down"]["kernel"])  # [..., m, w]
        down = jnp.zeros((*lead, hidden, width), self.dtype)
        down = down.at[..., :old_down.shape[-2], :old_width].set(old_down.astype(self.dtype))
        return {"gate": {"kernel": self.put(p["gate"]["kernel"], (*lead, width, hidden))},
                "up": {"kernel": self.put(p["up"]["kernel"], (*lead, width, hidden))},
                "down": {"kernel": down}}

    # -- decoder layers ----------------------------------------------------------------------
    def decoder_layer(self, p: dict, lead=()) -> dict:
        """One decoder block's params (stacked over `lead` layers, or a single block)."""
        o, n = self.old, self.new
        return {"attn_norm": {"scale": self.norm(p["attn_norm"]["scale"], n.d_model, self.gain, lead)},
                "qkv": {"kernel": self.qkv(p["qkv"]["kernel"], lead)},
                "out": {"kernel": self.attn_out(p["out"]["kernel"], lead)},
                "mlp_norm": {"scale": self.norm(p["mlp_norm"]["scale"], n.d_model, self.gain, lead)},
                "mlp": self.mlp(p["mlp"], n.d_model, n.mlp_dim, o.d_model, lead)}

    def decoder_layers(self, p: dict) -> list[dict]:
        """The scanned blocks [l, ...] -> L per-layer param trees: the trained layers first, then
        identity layers (zero attention output and MLP down projection: full cost, no effect)."""
        o, n = self.old, self.new
        trained = self.decoder_layer(p, lead=(o.n_layers,))
        layers = [jax.tree.map(lambda x, i=i: x[i], trained) for i in range(o.n_layers)]
        del trained
        identity = lambda path, x: (jnp.zeros_like(x) if path[-2].key in ("out", "down")  # noqa: E731
                                    else self.fill(x.shape))
        layers += [jax.tree_util.tree_map_with_path(identity, layers[0]) for _ in range(n.n_layers - o.n_layers)]
        return layers

    # -- vision -----------------------------------------------------------------------------
    def vision_attn(self, p: dict) -> dict:
        """flax MultiHeadDotProductAttention: query/key/value [w, h, hd] + bias, out [h, hd, w]."""
        o, n = self.old, self.new
        hd, new_hd = o.vision_width // o.vision_heads, n.vision_width // n.vision_heads
        w, new_w, h, new_h = o.vision_width, n.vision_width, o.vision_heads, n.vision_heads
        out = {}
        for name, scale in (("query", math.sqrt(new_hd / hd)), ("key", 1.0), ("value", 1.0)):
            zero_extra = name != "value"  # the trained heads' extra dims: zero in q and k
            kern = self.fill((new_w, new_h, new_hd))
            bias = self.fill((new_h, new_hd))
            if zero_extra:
                kern, bias = kern.at[:, :h].set(0), bias.at[:h].set(0)
            kern = kern.at[:w, :h, :hd].set((jnp.asarray(p[name]["kernel"], jnp.float32) * scale).astype(self.dtype))
            bias = bias.at[:h, :hd].set((jnp.asarray(p[name]["bias"], jnp.float32) * scale).astype(self.dtype))
            out[name] = {"kernel": kern, "bias": bias}
        ok = jnp.zeros((new_h, new_hd, new_w), self.dtype).at[:h, :hd, :w].set(
            jnp.asarray(p["out"]["kernel"]).astype(self.dtype))
        ob = jnp.zeros((new_w,), self.dtype).at[:w].set(jnp.asarray(p["out"]["bias"]).astype(self.dtype))
        out["out"] = {"kernel": ok, "bias": ob}
        return out

    def vision(self, p: dict) -> dict:
        o, n = self.old, self.new
        w, new_w = o.vision_width, n.vision_width
        pad = n.image_tokens - o.image_tokens
        pos = self.fill((1, n.image_tokens, new_w)).at[:, pad:].set(0)
        pos = pos.at[:, pad:, :w].set(jnp.asarray(p["pos"]).astype(self.dtype))
        out = {"pos": pos,
               "patchify": {"kernel": self.put(p["patchify"]["kernel"], (*p["patchify"]["kernel"].shape[:3], new_w),
                                               rest_zero=True),
                            "bias": self.put(p["patchify"]["bias"], (new_w,), rest_zero=True)},
               "out_norm": {"scale": self.norm(p["out_norm"]["scale"], new_w, self.vgain)}}
        for i in range(n.vision_layers):
            if i < o.vision_layers:
                attn, mlp = self.vision_attn(p[f"attn{i}"]), self.mlp(p[f"mlp{i}"], new_w, n.vision_mlp, w)
                norms = [self.norm(p[f"{k}{i}"]["scale"], new_w, self.vgain) for k in ("norm", "mlp_norm")]
            else:  # identity layers
                attn = {k: {"kernel": self.fill((new_w, n.vision_heads, new_w // n.vision_heads)),
                            "bias": self.fill((n.vision_heads, new_w // n.vision_heads))} for k in ("query", "key", "value")}
                attn["out"] = {"kernel": jnp.zeros((n.vision_heads, new_w // n.vision_heads, new_w), self.dtype),
                               "bias": jnp.zeros((new_w,), self.dtype)}
                mlp = {"gate": {"kernel": self.fill((new_w, n.vision_mlp))},
                       "up": {"kernel": self.fill((new_w, n.vision_mlp))},
                       "down": {"kernel": jnp.zeros((n.vision_mlp, new_w), self.dtype)}}
                norms = [jnp.ones((new_w,), self.dtype)] * 2
            out.update({f"attn{i}": attn, f"mlp{i}": mlp, f"norm{i}": {"scale": norms[0]},
                        f"mlp_norm{i}": {"scale": norms[1]}})
        if new_w != n.d_model:  # the projection to the decoder's width
            old_proj = (p["proj"]["kernel"] if "proj" in p else jnp.eye(w, o.d_model))
            proj = self.fill((new_w, n.d_model)).at[:, o.d_model:].set(0)
            out["proj"] = {"kernel": proj.at[:w, :o.d_model].set(jnp.asarray(old_proj).astype(self.dtype))}
        elif "proj" in p:
            raise ValueError("the target projects its vision tower to the decoder's width; the scale does not")
        return out


def with_layout(params, cfg: vla.VLAConfig, per_layer: bool):
    """(params, cfg) with the decoder's weights one array per layer ("layer0", ...) or stacked
    under a scan ("blocks"): the same function either way."""
    if per_layer == cfg.per_layer:
        return params, cfg
    params = dict(params)
    if per_layer:
        blocks = params.pop("blocks")
        params.update({f"layer{i}": jax.tree.map(lambda x, i=i: x[i], blocks) for i in range(cfg.n_layers)})
    else:
        layers = [params.pop(f"layer{i}") for i in range(cfg.n_layers)]
        params["blocks"] = jax.tree.map(lambda *xs: jnp.stack(xs), *layers)
    return params, dataclasses.replace(cfg, per_layer=per_layer)


def expand_target(params, cfg: vla.VLAConfig, name: str | TargetScale, dtype: str = "bfloat16", seed: int = 0):
    """(params, config) of target (params, cfg) expanded to scale `name` (`SCALES`), its
    parameters in `dtype` on the default device. "shipped" only casts to dtype."""
    new = dataclasses.replace(scaled_config(cfg, name), dtype=dtype)
    if _resolve(name) is None:
        return jax.tree.map(lambda x: x.astype(dtype), params), new
    e = _Expander(cfg, new, dtype, seed)
    d = cfg.d_model
    out = {"vision": e.vision(params["vision"]),
           **{f"layer{i}": layer for i, layer in enumerate(e.decoder_layers(params["blocks"]))},
           "final_norm": {"scale": e.norm(params["final_norm"]["scale"], new.d_model, e.gain)},
           "embed": {"embedding": e.put(params["embed"]["embedding"], (new.vocab, new.d_model)).at[:, d:].set(0)},
           "head": {"kernel": e.put(params["head"]["kernel"], (new.d_model, new.vocab))},
           "proprio_proj": {"kernel": e.put(params["proprio_proj"]["kernel"], (cfg.proprio_dim, new.d_model),
                                            rest_zero=True),
                            "bias": e.put(params["proprio_proj"]["bias"], (new.d_model,), rest_zero=True)}}
    return out, new


def expand_drafter(dparams, cfg: vla.VLAConfig, name: str | TargetScale, dtype: str = "bfloat16", seed: int = 1):
    """The drafter of target config cfg expanded to scale `name`: an EAGLE head of the
    expanded width (one decoder layer, its input projection from [embedding, feature])."""
    if _resolve(name) is None:
        return jax.tree.map(lambda x: x.astype(dtype), dparams)
    new = dataclasses.replace(scaled_config(cfg, name), dtype=dtype)
    e = _Expander(cfg, new, dtype, seed)
    d, big = cfg.d_model, new.d_model
    fc = jnp.asarray(dparams["fc"]["kernel"], jnp.float32)  # [2d, d]: rows embedding dims, then feature dims
    kern = e.fill((2 * big, big)).at[:, d:].set(0)
    kern = kern.at[:d, :d].set(fc[:d].astype(e.dtype)).at[big:big + d, :d].set(fc[d:].astype(e.dtype))
    return {"fc": {"kernel": kern, "bias": e.put(dparams["fc"]["bias"], (big,), rest_zero=True)},
            "block": e.decoder_layer(dparams["block"]),
            "norm": {"scale": e.norm(dparams["norm"]["scale"], big, e.gain)}}
