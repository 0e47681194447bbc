"""The decoding methods, one record each (`Method`), registered by name so the evaluator,
sweeps and benchmarks can say `--method=NAME`.

A method's record says what it is (`name`), its default configuration (`default`: the
runtime config it runs with when given no settings; a VLA method's is a `Config`, its
numerics and its decoder's config), what it loads (target checkpoint, drafter, datastore),
whether it looks at the camera image, and whether it chooses a draft budget from measured
costs. Its settings, the entry points' flags and the sweep keys (`heisd:budget=fixed`), are
the fields of its config that `SETTINGS` names: their types and defaults are the config's,
and given settings replace those fields (`config`), over a datastore's calibration for the
hybrid methods, with what they imply (`_implied`: acceptance=strict given is lossless unless
asked otherwise, verify-skip needs its source's candidates). `make_policy`
builds its `envs.rollout.Policy` for an env: the scripted expert (an upper bound, no model)
or a VLA decoding method over the shipped (or given) checkpoints.
"""

from __future__ import annotations

import dataclasses
import json
import functools
import typing
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs import camera, expert, language, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from envs.rollout import Policy
from heisd_jax import acceptance, budget, checkpoint, cost_model, hybrid, kinematics, retrieval, scale, spec_decode, vla
from heisd_jax.harness import vla_policy

DTYPES = ("float32", "bfloat16")
BOUNDARY_FILE = "boundary.json"  # written into the datastore directory by experiments.calibrate_boundary


def _load_target(env: TabletopEnv, checkpoint_path: str | Path):
    params, cfg, tok, _ = checkpoint.load_policy(checkpoint_path, text_vocab=language.VOCAB)
    if cfg.image_shape != env.config.camera.image_shape:
        raise ValueError(f"checkpoint {checkpoint_path} expects images of shape {cfg.image_shape} "
                         f"({cfg.n_views} view(s)), the env renders {env.config.camera.image_shape}")
    return params, cfg, tok


def in_dtype(cfg: vla.VLAConfig, dtype: str, *params, matmul_precision: str | None = None):
    """The model config and parameter trees in compute dtype `dtype` (float32, bfloat16):
    parameters and KV caches are stored in it; with `matmul_precision`, the config's precision
    of float32 matrix products too. Call after loading (fingerprints, which tie drafters and
    datastores to a target, are of the stored float32 parameters)."""
    if dtype not in DTYPES:
        raise ValueError(f"unknown dtype {dtype!r}; valid: {', '.join(DTYPES)}")
    cast = lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x  # noqa: E731
    cfg = dataclasses.replace(cfg, dtype=dtype, matmul_precision=matmul_precision or cfg.matmul_precision)
    return (cfg, *(jax.tree.map(cast, p) for p in params))


@dataclasses.dataclass(frozen=True)
class Numerics:
    """How a VLA method's models compute: the parameters' and KV caches' dtype (None: the
    target's own, the dtype its checkpoint stores its parameters in: float32 for the shipped
    target, bfloat16 for one exported with `train --export_param_dtype=bfloat16`), the precision
    of float32 matrix products, the architecture the target is expanded to, whether the
    inference passes are unrolled, how the prefill attends (`vla.VLAConfig.attention`) and how
    the vision tower patchifies (`vla.VLAConfig.patchify`)."""
    dtype: str | None = None
    matmul_precision: str = vla.VLAConfig.matmul_precision
    target_scale: str = scale.SHIPPED
    unroll: bool = vla.VLAConfig.unroll
    attention: str = vla.AUTO_ATTENTION
    patchify: str = vla.VLAConfig.patchify


@dataclasses.dataclass(frozen=True)
class Config:
    """A VLA method's runtime configuration: its numerics and its decoder's config (None:
    greedy AR; `spec_decode.SpecConfig`: drafter trees; `hybrid.HybridConfig`: retrieval and
    drafter drafts)."""
    numerics: Numerics = Numerics()
    decode: spec_decode.SpecConfig | hybrid.HybridConfig | None = None


def stored_dtype(params, default: str = "float32") -> str:
    """The dtype a loaded target's floating-point parameters come in (its checkpoint's);
    `default` for a tree that holds none."""
    kinds = {str(x.dtype) for x in jax.tree.leaves(params) if jnp.issubdtype(x.dtype, jnp.floating)}
    if not kinds:
        return default
    if len(kinds) != 1 or not kinds <= set(DTYPES):
        raise ValueError(f"target parameters in {sorted(kinds)}: expected all in one of {', '.join(DTYPES)}")
    return kinds.pop()


def in_numerics(cfg: vla.VLAConfig, numerics: Numerics, target, drafter=None):
    """The target (and its drafter) at a method's numerics: expanded to `target_scale`
    (`heisd_jax.scale`), in their dtype (by default the target's own, `stored_dtype`) and
    matmul precision, the inference passes unrolled or not. Returns (cfg, target params[,
    drafter params]); the cfg is `numerics_config`'s."""
    dtype = numerics.dtype or stored_dtype(target, cfg.dtype)
    out_cfg = numerics_config(cfg, numerics, dtype)  # refuses a scale smaller than the target first
    if scale.scaled_config(cfg, numerics.target_scale) is not cfg:
        scale.check_fits(cfg, numerics.target_scale, dtype)
        dparams = None if drafter is None else scale.expand_drafter(drafter, cfg, numerics.target_scale, dtype)
        target, _ = scale.expand_target(target, cfg, numerics.target_scale, dtype)
        drafter = dparams
    _, *params = in_dtype(cfg, dtype, *(p for p in (target, drafter) if p is not None))
    return (out_cfg, *params)


def numerics_config(cfg: vla.VLAConfig, numerics: Numerics, dtype: str) -> vla.VLAConfig:
    """The model config of the target `cfg` at `numerics` in compute dtype `dtype` (what
    `in_numerics` returns), without making any parameters: what a decode-cost table is keyed by."""
    vla.check_attention(numerics.attention)
    big = scale.scaled_config(cfg, numerics.target_scale)
    out = dataclasses.replace(big, dtype=dtype, matmul_precision=numerics.matmul_precision or big.matmul_precision,
                              unroll=numerics.unroll, attention="xla", patchify=numerics.patchify)
    return dataclasses.replace(out, attention=vla.resolve_attention(numerics.attention, out))


def _show_trees(trees: tuple[tuple[int, int, int], ...]) -> str:
    return "/".join("x".join(map(str, t)) for t in trees)


@dataclasses.dataclass(frozen=True)
class Setting:
    """One config field settable by name: the flag and sweep key `key`, its help line, its
    valid values if a choice, the (key, value) it is only used with, and for a field whose
    value is not a plain number, string or bool, how it is read from and written as text.
    `settings` binds it to a method's config: where the field sits (`path`), its type (`kind`) and
    the method's default (as text where `show` is given)."""
    key: str
    help: str
    choices: tuple[str, ...] | None = None
    only_with: tuple[str, object] | None = None
    parse: Callable[[str], object] | None = None
    show: Callable[[object], str] | None = None
    path: tuple[str, ...] = ()
    kind: type = str
    default: object = None


# The settable fields of the configs, by class and field name (the fields not named here keep
# their config's value). Flags, sweep keys, their types and each method's defaults come from
# the method's config (`settings`), so each default is the config's, written once.
_S = Setting
_CALIBRATED = "the datastore's calibration, if it has one, replaces the default"
SETTINGS: dict[type, dict[str, Setting]] = {
    Numerics: {
        "dtype": _S("dtype", "Parameters and KV cache in this dtype (default: the target checkpoint's own, the "
                    "dtype it stores its parameters in).", DTYPES),
        "matmul_precision": _S("matmul_precision", "float32 matrix products: 'float32' in full float32 (the same "
                               "tokens at every batch size), 'default' at XLA's choice (TF32 tensor cores for some "
                               "shapes on recent NVIDIA GPUs), 'tf32' (GPUs) or 'bf16': that tensor-core algorithm "
                               "for every product, float32 accumulation; 'tf32x3' (GPUs), 'bf16x3', 'bf16x6', "
                               "'bf16x9' (GPUs): 3 to 9 such products per product, near float32's rounding; "
                               "'tf32_rounded': every operand rounded to TF32 first, then TF32 tensor cores (GPUs) "
                               "or float32, whose products are then exact, so every kernel forms the same ones; "
                               "'bf16_invariant' (either dtype): every product on bf16 operands by one fixed-tile "
                               "kernel and every sum in a fixed order, so a state's tokens do not depend on the "
                               "batch (heisd_jax.invariant_products).",
                               vla.MATMUL_PRECISIONS),
        "target_scale": _S("target_scale", "The target (and drafter) expanded, function-preserving, to a larger "
                           "architecture (heisd_jax.scale, docs/scale.md): the shipped target's tokens at a larger "
                           "model's pass costs.", scale.SCALE_NAMES),
        "unroll": _S("unroll", "Inference passes with the decoder layers (and AR's token loop) unrolled: one "
                     "straight-line program per pass instead of a loop the host drives layer by layer on a GPU; "
                     "compiles several times longer, runs slower on a CPU, and on a GPU is faster inside a compiled "
                     "loop but slower called from Python (BENCHMARKS.md)."),
        "attention": _S("attention", "How the prefill attends in the decoder: 'xla' (products and softmax as XLA "
                        "fuses them), 'cudnn' (cuDNN's fused attention; a GPU, bfloat16): at the 7B scale the "
                        "prefill 1.1x faster (docs/scale.md), or 'auto': cudnn for an expanded target "
                        "(target_scale) on a GPU in 16 bits without bf16_invariant products, xla elsewhere "
                        "(vla.resolve_attention).", (vla.AUTO_ATTENTION, *vla.ATTENTIONS)),
        "patchify": _S("patchify", "How the vision tower cuts the image into patch embeddings, the same function and "
                       "parameters: 'conv' (a convolution; cuDNN's on a GPU) or 'dense' (one matrix product over the "
                       "patches, which a CUDA graph holds, so the decode step's conditionals need not run from the "
                       "host; vla.Patchify).", vla.PATCHIFIES),
    },
    spec_decode.SpecConfig: {
        "top_k": _S("top_k", "Draft tree: children kept per level (EAGLE-2 top-k)."),
        "depth": _S("depth", "Draft tree: depth."),
        "total_tokens": _S("total_tokens", "Draft tree: nodes verified per round (<= top_k * depth)."),
        "acceptance": _S("acceptance", "Drafter trees: acceptance rule. Given as strict: lossless, every "
                         "other rule follows (relax_bins 0, retrieval_acceptance strict, verify-skip off) unless "
                         "given; heisd's default is strict trees after relaxed candidates. Given as token_relaxed: "
                         f"relax_bins {acceptance.RELAX_BINS} unless given.", acceptance.TOKEN_RULES),
        "relax_bins": _S("relax_bins", "token_relaxed: accept a draft within this many bins of the target's "
                         "choice (0 with strict acceptance)."),
        "spread": _S("spread_tree", "token_relaxed: a node's children ranked by the drafter's probability "
                     "mass within relax_bins of them and kept more than 2 x relax_bins apart."),
    },
    hybrid.HybridConfig: {
        "mode": _S("mode", "hybrid (kinematic boundary) or one mode at every step.", hybrid.MODES),
        "acceptance": _S("retrieval_acceptance", "Acceptance rule for retrieval drafts (acceptance=strict given: "
                         "strict unless given).", acceptance.ACTION_RULES),
        "relax_bins": _S("retrieval_relax_bins", "token_relaxed retrieval acceptance: bins."),
        "n_candidates": _S("n_candidates", "Retrieved actions verified per step (0: no datastore query, the "
                           "recent actions alone, verify-skip from retrieval off unless given)."),
        "recent_candidates": _S("recent_candidates", "The env's own last executed actions verified as further "
                                "candidates each retrieval step (our design; 0: verify-skip from recent actions "
                                "off unless given)."),
        "max_dist": _S("max_dist", "Candidates with a squared key distance above this are invalid."),
        "verify": _S("verify", "Retrieval drafts verified inside the prefill or in a second pass.", hybrid.VERIFY),
        "continuation": _S("continuation", "budget=fixed: what decodes the rest of an action after the prefill and "
                           "its accepted candidate prefix: drafter rounds or single-token AR passes (no drafter).",
                           hybrid.CONTINUATION, only_with=("budget", "fixed")),
        "row_buckets": _S("row_buckets", "Rows that need a target pass (not skipped) run gathered in the smallest "
                          "of this many batch fractions that holds them (1: always the whole batch; k > 1 compiles "
                          "the decode k times)."),
    },
    acceptance.SeqRelaxedConfig: {
        "r_max": _S("r_max", "seq_relaxed: no token further than this many bins from the target's (the paper's 15 "
                    "costs closed-loop success on our suites)."),
        "r_seq": _S("r_seq", "seq_relaxed: bound on the cumulative bin distance of the accepted prefix (the paper: "
                    "42)."),
    },
    acceptance.SkipConfig: {
        "enabled": _S("skip", "Verify-skip: a confident retrieval-mode row executes a candidate without a target "
                      "pass (off with acceptance=strict given, or without the candidates its source needs, unless "
                      "given)."),
        "source": _S("skip_source", "Verify-skip: what a skipped step executes: the env's last action again "
                     "(recent), or the datastore's top candidate (retrieval, the paper's; rarely confident enough "
                     "to fire on the shipped stack).", acceptance.SKIP_SOURCES),
        "n_confirm": _S("n_confirm", "Verify-skip from recent actions: the last this many verified steps each "
                        "accepted their previous action whole."),
        "k_skip": _S("k_skip", "Verify-skip: at most this many consecutive skipped target passes (longer runs of "
                     "repeated actions cost closed-loop success)."),
        "max_metric": _S("skip_max_metric", "Verify-skip only where the kinematic metric M is at most this (coarse "
                         "motion; inf: wherever the row is in retrieval mode)."),
        "eps": _S("skip_eps", f"Verify-skip: nearest-key squared distance under which retrieval is trusted "
                  f"({_CALIBRATED})."),
        "r_agree": _S("r_agree", "Verify-skip: the top candidates agree within this many bins."),
        "repeat_r_max": _S("repeat_r_max", "Verify-skip from recent actions: a verified step also counts as a "
                           "repeat when the target's action is within this many bins of the last one on every token "
                           "(with repeat_r_seq; unset: only an executed action equal to the last one), so tight "
                           "r_max / r_seq can keep the executed actions on the target's while the skip still "
                           "fires where the motion repeats loosely."),
        "repeat_r_seq": _S("repeat_r_seq", "Verify-skip from recent actions: with repeat_r_max, the bound on the "
                           "cumulative bin distance of that repeat."),
    },
    kinematics.BoundaryConfig: {
        "tau_on": _S("tau_on", f"Boundary: metric above which the drafter mode starts ({_CALIBRATED})."),
        "tau_off": _S("tau_off", f"Boundary: metric below which the retrieval mode starts ({_CALIBRATED})."),
        "min_dwell": _S("min_dwell", f"Boundary: control steps a mode holds at least ({_CALIBRATED})."),
    },
    budget.BudgetConfig: {
        "mode": _S("budget", "Draft budget chosen per step from measured costs (auto) or the one fixed tree "
                   "(fixed).", budget.BUDGETS),
        "trees": _S("budget_trees", "budget=auto: draft trees to choose from besides AR, TOPKxDEPTHxTOTAL "
                    "separated by '/' (a top_k/depth/total_tokens tree given instead: that tree alone).",
                    only_with=("budget", "auto"), parse=budget.parse_trees, show=_show_trees),
        "forget": _S("budget_forget", "budget=auto: per unchosen step, share by which an option's estimate "
                     "returns to its long-run mean (0: never).", only_with=("budget", "auto")),
        "margin": _S("budget_margin", "budget=auto: a drafting option must be predicted this much faster than AR "
                     "to be chosen, and a larger tree this much faster than the next smaller one.",
                     only_with=("budget", "auto")),
        "max_batch": _S("budget_max_batch", "budget=auto: the largest batch size (rows per device) at which "
                        "drafting options run; above it the method decodes as plain AR.",
                        only_with=("budget", "auto")),
    },
    expert.ExpertConfig: {f.name: _S(f.name, "The scripted expert's " + f.name.replace("_", " ") + ".")
                          for f in dataclasses.fields(expert.ExpertConfig)},
}
# Why a setting is only used with another's value (its error message says it).
_ONLY_WITH_WHY = {"continuation": " (budget=auto chooses per step between AR after the verified candidates, option "
                                  "ar+retrieval, and the drafter trees)"}


# Named sets of settings, per method: the sweep key and flag `preset` (`heisd:preset=batch16`,
# `--preset=batch16`) stands for its settings, and settings given beside it replace its own.
# Each is the configuration docs/scale.md measured fastest at the 7B scale at that batch size
# with every suite's success within 2 points of AR's; the default (`budget=auto`) is the
# configuration for a target of unknown costs. A result records the settings, not the name.
PRESET = "preset"
PRESETS: dict[str, dict[str, dict]] = {
    "heisd": {
        # One fixed 4x2x8 drafter tree after the verified candidates: no chooser to run.
        "batch1": {"budget": "fixed", "top_k": 4, "depth": 2, "total_tokens": 8},
        # Verify-skipped rows out of the batch (row_buckets), one recent candidate in the
        # prefill, single-token passes after it, and a tight acceptance that keeps the executed
        # actions on the target's, with loose repeat bounds so verify-skip still fires.
        "batch16": {"budget": "fixed", "continuation": "ar", "n_candidates": 0, "recent_candidates": 1,
                    "r_max": 2, "r_seq": 6, "repeat_r_max": 9, "repeat_r_seq": 24, "row_buckets": 4},
    },
}


def _with_preset(name: str, given: dict) -> dict:
    """`given` with its `preset` replaced by that preset's settings (the given ones win)."""
    if PRESET not in given:
        return given
    rest = {k: v for k, v in given.items() if k != PRESET}
    named = PRESETS.get(name, {})
    if given[PRESET] not in named:
        raise ValueError(f"method {name!r}: unknown preset {given[PRESET]!r}; valid: {', '.join(named) or 'none'}")
    return {**named[given[PRESET]], **rest}


def _bind(cfg, path: tuple[str, ...] = ()):
    """The settings of config `cfg` (a tree of dataclasses), key -> bound `Setting`, in field order."""
    out: dict[str, Setting] = {}
    hints = typing.get_type_hints(type(cfg))
    table = SETTINGS.get(type(cfg), {})
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.name in table:
            s = table[f.name]
            kind = str if s.parse else next((a for a in typing.get_args(hints[f.name]) if a is not type(None)),
                                            hints[f.name])
            found = {s.key: dataclasses.replace(s, path=path + (f.name,), kind=kind,
                                                default=s.show(value) if s.show else value)}
        elif dataclasses.is_dataclass(value):
            found = _bind(value, path + (f.name,))
        else:
            continue
        clash = set(found) & set(out)
        if clash:
            raise ValueError(f"settings {sorted(clash)} name two fields of {type(cfg).__name__}")
        out.update(found)
    return out


def settings(name: str) -> dict[str, Setting]:
    """The settings of method `name`, key -> `Setting` (its path in the method's config, type,
    default, help, choices): its flags and sweep keys."""
    return _bind(get(name).default)


def _values(bound: dict[str, Setting], cfg) -> dict:
    """Every setting's value in config `cfg`, as given (text where the field is not a plain value)."""
    out = {}
    for key, s in bound.items():
        value = functools.reduce(getattr, s.path, cfg)
        out[key] = s.show(value) if s.show else value
    return out


def settings_of(name: str, cfg) -> dict:
    """The settings in effect in config `cfg` of method `name`, key -> value as given (a
    setting only used with another's value left out where that does not hold, and one whose
    value is None, which stands for a default resolved at build time, e.g. the target's own
    dtype): `config(name, settings_of(name, c)) == c` for a config `c` reached by settings."""
    bound = settings(name)
    out = _values(bound, cfg)
    return {k: v for k, v in out.items() if v is not None
            and (not bound[k].only_with or out[bound[k].only_with[0]] == bound[k].only_with[1])}


def _replaced(cfg, updates: dict[tuple[str, ...], object]):
    """`cfg` with the fields at the given paths replaced; each nested config is rebuilt (and
    checked) once, with all its changes."""
    here = {p[0]: v for p, v in updates.items() if len(p) == 1}
    below: dict[str, dict] = {}
    for p, v in updates.items():
        if len(p) > 1:
            below.setdefault(p[0], {})[p[1:]] = v
    here.update({k: _replaced(getattr(cfg, k), sub) for k, sub in below.items()})
    return dataclasses.replace(cfg, **here) if here else cfg


def _cast(key: str, value, kind):
    if kind is bool and isinstance(value, str):
        if value.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"setting {key}={value!r} is not a boolean (true/false)")
        return value.lower() in ("true", "1")
    if kind is int and isinstance(value, float) and value.is_integer():
        value = int(value)
    try:
        return kind(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"setting {key}={value!r} is not a {kind.__name__}") from e


def _implied(values: dict, given: dict) -> dict:
    """The settings that follow from others, where not given themselves: strict acceptance,
    given, means lossless (relax_bins 0, strict retrieval acceptance, verify-skip off; heisd's
    default trees are strict too, after relaxed candidates); token_relaxed acceptance, given,
    means relax_bins `acceptance.RELAX_BINS`; verify-skip needs its source's candidates (the
    datastore's, or the recent actions); a draft tree given by top_k/depth/total_tokens is the
    one tree budget=auto chooses from."""
    out = {}
    if given.get("acceptance") == "strict":
        out.update(relax_bins=0, retrieval_acceptance="strict", skip=False)
    if given.get("acceptance") == "token_relaxed" and not values.get("relax_bins"):
        out["relax_bins"] = acceptance.RELAX_BINS
    if "skip" in values and ((values["n_candidates"] == 0 and values["skip_source"] == "retrieval")
                             or (values["recent_candidates"] == 0 and values["skip_source"] == "recent")):
        out["skip"] = False
    if values.get("budget") == "auto" and any(k in given for k in ("top_k", "depth", "total_tokens")):
        out["budget_trees"] = _show_trees(((values["top_k"], values["depth"], values["total_tokens"]),))
    return {k: v for k, v in out.items() if k in values and k not in given}


def _calibrated(cfg, calibration: dict | None):
    """`cfg` with a datastore's calibration (`load_calibration`): metric scales, boundary
    thresholds, skip_eps. Only a hybrid method's config has them."""
    cal = calibration or {}
    if not isinstance(getattr(cfg, "decode", None), hybrid.HybridConfig) or not cal:
        return cfg
    up = {("decode", "boundary", k): v for k, v in cal.get("boundary", {}).items()}
    if "metric_scales" in cal:
        up[("decode", "metric", "scales")] = tuple(cal["metric_scales"])
    if "skip_eps" in cal:
        up[("decode", "skip", "eps")] = cal["skip_eps"]
    return _replaced(cfg, up)


def _config(name: str, given: dict, calibration: dict | None):
    base = _calibrated(get(name).default, calibration)
    bound = settings(name)
    values = {**_values(bound, base), **given}
    values.update(_implied(values, given))
    return _replaced(base, {s.path: s.parse(values[k]) if s.parse else values[k] for k, s in bound.items()})


def check_settings(name: str, given: dict) -> dict:
    """A method's given settings, typed and validated against its settings (a clear error
    naming the valid keys and values), before anything loads or compiles; a `preset` among
    them is replaced by its settings (`PRESETS`)."""
    bound = settings(name)
    given = _with_preset(name, given)
    unknown = sorted(set(given) - set(bound))
    if unknown:
        raise ValueError(f"method {name!r}: unknown settings {unknown}; valid: {', '.join(bound) or 'none'}")
    out = {k: _cast(k, v, bound[k].kind) for k, v in given.items()}
    for key, value in out.items():
        s = bound[key]
        if s.choices and value not in s.choices:
            raise ValueError(f"unknown {key} {value!r}; valid: {', '.join(s.choices)}")
    values = {**{k: s.default for k, s in bound.items()}, **out}
    for key in out:
        if bound[key].only_with:
            other, wanted = bound[key].only_with
            if values[other] != wanted:
                raise ValueError(f"{key} is only used with {other}={wanted}{_ONLY_WITH_WHY.get(key, '')}")
    _config(name, out, None)
    return out


def config(name: str, given: dict | None = None, calibration: dict | None = None):
    """The runtime config of method `name`: its default config, a datastore's `calibration`
    over it (metric scales, boundary thresholds, skip_eps), then the settings `given`
    (checked) and the settings they imply (`_implied`)."""
    return _config(name, check_settings(name, given or {}), calibration)


def load_calibration(datastore_path: str | Path, meta: dict) -> dict:
    """Metric scales (from the datastore build) and boundary thresholds (from
    experiments.calibrate_boundary, if it ran) of a datastore."""
    cal = {}
    if "metric_scales" in meta:
        cal["metric_scales"] = meta["metric_scales"]
    f = Path(datastore_path) / BOUNDARY_FILE
    if f.exists():
        b = json.loads(f.read_text())
        cal["boundary"] = {k: b[k] for k in ("tau_on", "tau_off", "min_dwell") if k in b}
        if "skip_eps" in b:
            cal["skip_eps"] = b["skip_eps"]
    return cal

def _build_expert(env: TabletopEnv, paths: dict, given: dict, **_) -> Policy:
    return expert.policy(env, config("expert", given))


def _build_ar(env: TabletopEnv, paths: dict, given: dict, **_) -> Policy:
    params, cfg, tok = _load_target(env, paths["checkpoint"])
    cfg, params = in_numerics(cfg, config("ar", given).numerics, params)
    return vla_policy.decoding_policy("ar", params, cfg, tok, vla_policy.ar)


def _build_drafter(env: TabletopEnv, paths: dict, given: dict, **_) -> Policy:
    run = config("drafter", given)
    spec = run.decode
    params, cfg, tok = _load_target(env, paths["checkpoint"])
    spec.check_fits(cfg)
    dparams, _ = checkpoint.load_drafter(paths["drafter"], cfg, params)
    cfg, params, dparams = in_numerics(cfg, run.numerics, params, dparams)
    return vla_policy.decoding_policy("drafter", {"target": params, "drafter": dparams}, cfg, tok,
                                      vla_policy.drafter_sd(spec), spec=spec)


def _as_ar(name: str, params, cfg: vla.VLAConfig, tok, table) -> Policy:
    """A budget=auto method where drafting cannot pay: AR's decode (program and tokens)."""
    policy = vla_policy.decoding_policy(name, params, cfg, tok, vla_policy.ar)
    return dataclasses.replace(policy, meta=dict(policy.meta, cost_table=table, runs_as_ar=True))


def load_hybrid(name: str, paths: dict, given: dict, env: TabletopEnv | None = None):
    """What a hybrid method (`name`: retrieval or heisd) runs with: the target, drafter and
    datastore at `paths` ("checkpoint", "drafter", "datastore"), its config at the settings
    `given` (checked) with the datastore's calibration, in the settings' numerics. Returns
    ({"target", "drafter", "store"}, model config, tokenizer, HybridConfig, key spec,
    datastore meta). With `env`, refuses a target that does not take its images or a
    datastore without entries for some of its tasks."""
    given = check_settings(name, given)
    if env is None:
        params, cfg, tok, _ = checkpoint.load_policy(paths["checkpoint"], text_vocab=language.VOCAB)
    else:
        params, cfg, tok = _load_target(env, paths["checkpoint"])
    dparams, _ = checkpoint.load_drafter(paths["drafter"], cfg, params)
    store, key_spec, meta = retrieval.load(paths["datastore"], tok, checkpoint.fingerprint(params))
    missing = [] if env is None else \
        sorted(set(env.global_index.tolist()) - set(np.unique(np.asarray(store.task)).tolist()))
    if missing:
        raise ValueError(f"datastore {paths['datastore']} has no entries for tasks "
                         f"{[tasks_lib.ALL_TASKS[i].name for i in missing]}; rebuild it from demos of those tasks")
    run = _config(name, given, load_calibration(paths["datastore"], meta))
    hcfg = run.decode
    hcfg.check_fits(cfg)
    cfg, params, dparams = in_numerics(cfg, run.numerics, params, dparams)
    return {"target": params, "drafter": dparams, "store": store}, cfg, tok, hcfg, key_spec, meta


def _build_hybrid(name: str):
    def build(env: TabletopEnv, paths: dict, given: dict, *, batch_size: int | None = None,
              cost_cache: str | Path | None = cost_model.DEFAULT_CACHE, calibrate_costs: bool = False,
              log: Callable[[str], None] = print) -> Policy:
        all_params, cfg, tok, hcfg, key_spec, _ = load_hybrid(name, paths, given, env)
        params = all_params["target"]
        table = None
        if hcfg.budget.mode == "auto":
            if batch_size is None or batch_size < 1:
                raise ValueError(f"budget=auto measures decode costs at the batch size in use: pass batch_size "
                                 f"(rows per device), got {batch_size}")
            if not hcfg.budget.drafts_at(batch_size):
                log(f"{name}: batch {batch_size} is above budget_max_batch {hcfg.budget.max_batch}: decoding with "
                    f"plain AR (where a prefill costs in proportion to its rows, as at 7B, preset=batch16 takes "
                    f"verify-skipped rows out of it: docs/scale.md)")
                return _as_ar(name, params, cfg, tok, table)
            table = cost_model.load_or_calibrate(all_params, cfg, hcfg, batch_size, cost_cache, log,
                                                  measure=calibrate_costs)
            all_params["costs"] = table.costs()
            opts = budget.options(hcfg.budget, hcfg.mode)
            if hcfg.row_buckets == 1 and budget.only_ar(all_params["costs"], opts, hcfg.budget.margin):
                # No option can beat AR at this batch size, and a skipped row saves nothing while
                # its batch-mates decode: HeiSD is plain AR here, program and tokens.
                log(f"{name}: at batch {batch_size} the cost table leaves no draft option that can beat AR by the "
                    f"{hcfg.budget.margin:.0%} margin: decoding with plain AR")
                return _as_ar(name, params, cfg, tok, table)
        policy = vla_policy.hybrid_policy(name, all_params, cfg, tok, hcfg, key_spec, env.global_index)
        return dataclasses.replace(policy, meta=dict(policy.meta, cost_table=table))
    return build


@dataclasses.dataclass(frozen=True)
class Method:
    """One decoding method: everything the evaluator needs to know about it."""
    name: str
    default: Config | expert.ExpertConfig  # what it runs at no settings; its fields are the settings (`settings`)
    loads: tuple[str, ...]  # what it reads: "checkpoint" (target VLA), "drafter", "datastore"
    renders: bool  # looks at the camera image (the expert does not: render off, faster)
    budget: bool  # may choose its draft budget from measured costs (takes batch_size, cost tables)
    build: Callable[..., Policy]  # (env, paths, given settings, **budget options) -> Policy
    # Of `loads`, the files that reach the compiled programs only as the policy's parameters
    # (an input) and its meta (part of a program's key): the executable store leaves their
    # digests out of its key, so checkpoints of one architecture and tokenizer share programs.
    shares_programs: tuple[str, ...] = ()


DEFAULT_PATHS = {"checkpoint": vla_policy.DEFAULT_CHECKPOINT, "drafter": vla_policy.DEFAULT_DRAFTER,
                 "datastore": vla_policy.DEFAULT_DATASTORE}
METHODS: dict[str, Method] = {m.name: m for m in (
    Method("expert", expert.ExpertConfig(), (), renders=False, budget=False, build=_build_expert),
    Method("ar", Config(), ("checkpoint",), renders=True, budget=False, build=_build_ar, shares_programs=("checkpoint",)),
    Method("drafter", Config(decode=spec_decode.SpecConfig()), ("checkpoint", "drafter"), renders=True, budget=False,
           build=_build_drafter),
    # Retrieval drafts verified every step, drafter SD for the rest of each action: the paper's
    # retrieval side alone, token-wise relaxed, without verify-skip.
    Method("retrieval", Config(decode=dataclasses.replace(hybrid.PAPER, mode="retrieval", acceptance="token_relaxed",
                                                          skip=dataclasses.replace(hybrid.PAPER.skip, enabled=False))),
           ("checkpoint", "drafter", "datastore"), renders=True, budget=True, build=_build_hybrid("retrieval")),
    # HeiSD: the kinematic boundary picks retrieval or drafter drafts per step; verify-skip,
    # sequence-wise relaxed acceptance of retrieved actions, strict drafter trees after them,
    # a draft budget chosen from measured costs.
    Method("heisd", Config(decode=hybrid.HybridConfig()), ("checkpoint", "drafter", "datastore"), renders=True,
           budget=True, build=_build_hybrid("heisd")),
)}
DECODING_METHODS = tuple(name for name, m in METHODS.items() if "checkpoint" in m.loads)  # the VLA methods


def get(name: str) -> Method:
    """The record of method `name` (a clear error naming the valid ones)."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    return METHODS[name]


def env_config(name: str, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT) -> EnvConfig:
    """The env settings method `name` runs under: the camera views and size its checkpoint
    was trained on (read from the checkpoint's metadata), no rendering for the expert."""
    if not get(name).renders:
        return EnvConfig(render=False)
    cfg = checkpoint.read_config(checkpoint_path)
    if cfg.n_views > len(camera.VIEWS):
        raise ValueError(f"checkpoint {checkpoint_path} expects {cfg.n_views} views; the env has {camera.VIEWS}")
    return EnvConfig(camera=camera.CameraConfig(height=cfg.image_size, width=cfg.image_size, wrist=cfg.n_views > 1))


def make_policy(name: str, env: TabletopEnv, *, checkpoint: str | Path | None = None,
                drafter: str | Path | None = None, datastore: str | Path | None = None,
                batch_size: int | None = None, cost_cache: str | Path | None = cost_model.DEFAULT_CACHE,
                calibrate_costs: bool = False, log: Callable[[str], None] = print, **settings) -> Policy:
    """The policy of method `name`; `checkpoint`/`drafter`/`datastore` (default: the shipped
    ones) reach only the methods that load them, `settings` are the method's own (its
    settings: `settings(name)`). batch_size (rows per device), cost_cache and calibrate_costs
    (measure a missing decode-cost table now instead of failing) reach the methods with a
    draft budget."""
    method = get(name)
    given = check_settings(name, settings)
    paths = _paths(method, checkpoint=checkpoint, drafter=drafter, datastore=datastore)
    return method.build(env, paths, given, batch_size=batch_size, cost_cache=cost_cache,
                        calibrate_costs=calibrate_costs, log=log)


def numerics_ran(policy: Policy) -> dict:
    """How a built policy's model computes (`vla.NUMERICS` of its config: the dtype read from
    the checkpoint where none was given, `attention` resolved from auto), for a results file
    to say what ran; {} for a policy without a VLA (the expert)."""
    cfg = policy.meta.get("cfg")
    return {} if cfg is None else {k: getattr(cfg, k) for k in vla.NUMERICS}


def _paths(method: Method, **given: str | Path | None) -> dict[str, Path]:
    """The files `method` loads: those given, else the shipped ones."""
    return {k: Path(given[k] if given.get(k) is not None else DEFAULT_PATHS[k]) for k in method.loads}


def missing_cost_tables(name: str, batch_sizes, *, checkpoint: str | Path | None = None,
                        datastore: str | Path | None = None,
                        cost_cache: str | Path | None = cost_model.DEFAULT_CACHE, **settings) -> list[int]:
    """The batch sizes (rows per device) at which `make_policy(name, ..., batch_size=b,
    calibrate_costs=False)` would find no decode-cost table in `cost_cache` and raise
    `cost_model.MissingCostTable`: the method drafts there under budget=auto and the table of
    its device, model (at its numerics: `numerics_config`), settings and b is not cached. Read
    from configs and files alone (no parameters expanded, nothing compiled), so an entry point
    that runs something long before building its policies can refuse first."""
    method = get(name)
    given = check_settings(name, settings)
    if not method.budget:
        return []
    return _missing_cost_tables(name, _paths(method, checkpoint=checkpoint, datastore=datastore), given,
                                batch_sizes, cost_cache)


def check_fits(name: str, *, checkpoint: str | Path | None = None, **settings) -> None:
    """ValueError where method `name` at `settings` cannot decode with the target at
    `checkpoint`: its numerics cannot run with it (`numerics_config`: a scale smaller than the
    target, cuDNN's attention off a GPU or in float32), or its draft trees, or its retrieved and
    recent candidates, need more KV-cache slots than the target has (the check `make_policy`
    makes when it builds the policy). Read from the target's config alone (a datastore's
    calibration changes no tree or candidate count), so an entry point can refuse before it
    records or compiles anything."""
    method = get(name)
    given = check_settings(name, settings)
    if "checkpoint" in method.loads:
        _check_fits(name, _paths(method, checkpoint=checkpoint)["checkpoint"], given, "drafter" in method.loads)


def _check_fits(name: str, target: Path, given: dict, drafts: bool) -> None:  # apart: `checkpoint` is the module here
    cfg, run = checkpoint.read_config(target), _config(name, given, None)
    numerics_config(cfg, run.numerics, run.numerics.dtype or cfg.dtype)
    if drafts:
        run.decode.check_fits(cfg)


def _missing_cost_tables(name: str, paths: dict[str, Path], given: dict, batch_sizes, cost_cache) -> list[int]:
    run = _config(name, given, load_calibration(paths["datastore"], retrieval.read_meta(paths["datastore"])))
    drafting = [b for b in batch_sizes if run.decode.budget.mode == "auto" and run.decode.budget.drafts_at(b)]
    if not drafting:
        return []
    _, cfg, _, _ = checkpoint.load_policy(paths["checkpoint"], text_vocab=language.VOCAB)  # cfg.dtype: as stored
    cfg = numerics_config(cfg, run.numerics, run.numerics.dtype or cfg.dtype)
    return [b for b in drafting if cost_model.load_cached(cfg, run.decode, b, cost_cache, log=lambda _: None) is None]


def _value(v: str):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def parse_method_list(spec: str) -> list[tuple[str, dict]]:
    """'ar,drafter:acceptance=token_relaxed,relax_bins=9;heisd:skip=false' -> [(name,
    settings), ...] (a comma-separated key=value after NAME:... belongs to it), every
    method's settings checked (`check_settings`)."""
    parts: list[str] = []
    for tok in (t.strip() for t in spec.replace(";", ",").split(",")):
        if not tok:
            continue
        if "=" in tok and ":" not in tok and parts:
            parts[-1] += "," + tok
        else:
            parts.append(tok)
    out = []
    for part in parts:
        name, _, rest = part.partition(":")
        settings = {}
        for kv in filter(None, rest.split(",")):
            k, eq, v = kv.partition("=")
            if not eq:
                raise ValueError(f"method setting {kv!r} of {name!r} is not key=value")
            settings[k.strip()] = _value(v.strip())
        try:
            out.append((name, check_settings(name, settings)))
        except (TypeError, ValueError) as e:
            raise ValueError(f"method {part!r}: {e}") from e
    return out
