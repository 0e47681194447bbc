"""The decoding methods, one record each (`Method`), registered by name so the evaluator,
sweeps and benchmarks can say `--method=NAME`.

A method's record says what it is (`name`), its settings (a dataclass: field names are the
entry points' flags and the sweep keys, field defaults are the method's defaults, written
once here), what it loads (target checkpoint, drafter, datastore), whether it looks at the
camera image, and whether it chooses a draft budget from measured costs. `make_policy`
builds its `envs.rollout.Policy` for an env: the scripted expert (an upper bound, no model)
or a VLA decoding method over the shipped (or given) checkpoints.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from envs import camera, expert, language, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from envs.rollout import Policy
from heisd_jax import (acceptance, budget, checkpoint, cost_model, hybrid, kinematics, retrieval, scale, spec_decode,
                       vla, vla_policy)

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


def in_numerics(cfg: vla.VLAConfig, settings: "ARSettings", target, drafter=None):
    """The target (and its drafter) at a method's settings: expanded to `target_scale`
    (`heisd_jax.scale`), in their dtype and matmul precision, the inference passes unrolled
    or not. Returns (cfg, target params[, drafter params])."""
    big = scale.scaled_config(cfg, settings.target_scale)  # refuses a scale smaller than the target first
    if big is not cfg:
        scale.check_fits(cfg, settings.target_scale, settings.dtype)
        dparams = None if drafter is None else scale.expand_drafter(drafter, cfg, settings.target_scale, settings.dtype)
        target, cfg = scale.expand_target(target, cfg, settings.target_scale, settings.dtype)
        drafter = dparams
    cfg, *params = in_dtype(cfg, settings.dtype, *(p for p in (target, drafter) if p is not None),
                            matmul_precision=settings.matmul_precision)
    return (dataclasses.replace(cfg, unroll=settings.unroll), *params)


def _setting(default, help: str, choices: tuple[str, ...] | None = None):
    """A settings field: its default, its help line (the flag's), its valid values if a choice."""
    return dataclasses.field(default=default, metadata={"help": help, "choices": choices})


_SPEC, _HYB, _SEQ, _SKIP = spec_decode.SpecConfig, hybrid.HybridConfig, acceptance.SeqRelaxedConfig, acceptance.SkipConfig
# Module names that fields below shadow (`acceptance`, `budget`) in their class bodies:
TOKEN_RULES, ACTION_RULES, SKIP_SOURCES = acceptance.TOKEN_RULES, acceptance.ACTION_RULES, acceptance.SKIP_SOURCES
BUDGETS, _BUDGET = budget.BUDGETS, budget.BudgetConfig
_DEFAULT_TREES = "/".join("x".join(map(str, t)) for t in budget.DEFAULT_TREES)


@dataclasses.dataclass(frozen=True)
class ARSettings:
    """Greedy autoregressive decoding: the target's prefill, then one pass per token."""
    dtype: str = _setting("float32", "Parameters and KV cache in this dtype.", DTYPES)
    matmul_precision: str = _setting(vla.VLAConfig.matmul_precision, "float32 matrix products: 'float32' in full "
                                     "float32 (the same tokens at every batch size), 'default' at XLA's choice (TF32 "
                                     "tensor cores for some shapes on recent NVIDIA GPUs), 'tf32' (GPUs) or 'bf16': "
                                     "that tensor-core algorithm for every product, float32 accumulation; 'tf32x3' "
                                     "(GPUs), 'bf16x3', 'bf16x6', 'bf16x9' (GPUs): 3 to 9 such products per product, "
                                     "near float32's rounding; 'tf32_rounded': every operand rounded to TF32 first, "
                                     "then TF32 tensor cores (GPUs) or float32, whose products are then exact, so "
                                     "every kernel forms the same ones.",
                                     vla.MATMUL_PRECISIONS)
    target_scale: str = _setting(scale.SHIPPED, "The target (and drafter) expanded, function-preserving, to a "
                                 "larger architecture (heisd_jax.scale, docs/scale.md): the shipped target's tokens "
                                 "at a larger model's pass costs.", scale.SCALE_NAMES)
    unroll: bool = _setting(vla.VLAConfig.unroll, "Inference passes with the decoder layers (and AR's token loop) "
                            "unrolled: one straight-line program per pass instead of a loop the host drives layer by "
                            "layer on a GPU; compiles several times longer, runs slower on a CPU, and on a GPU is "
                            "faster inside a compiled loop but slower called from Python (BENCHMARKS.md).")


@dataclasses.dataclass(frozen=True)
class DrafterSettings(ARSettings):
    """Spec-VLA: EAGLE-2 draft trees from the drafter, verified by the target."""
    top_k: int = _setting(_SPEC.top_k, "Draft tree: children kept per level (EAGLE-2 top-k).")
    depth: int = _setting(_SPEC.depth, "Draft tree: depth.")
    total_tokens: int = _setting(_SPEC.total_tokens, "Draft tree: nodes verified per round (<= top_k * depth).")
    acceptance: str = _setting(_SPEC.acceptance, "Drafter trees: acceptance rule.", TOKEN_RULES)
    relax_bins: int = _setting(_SPEC.relax_bins, "token_relaxed: accept a draft within this many bins of the "
                               "target's choice (strict acceptance: 0 unless given).")


@dataclasses.dataclass(frozen=True)
class RetrievalSettings(DrafterSettings):
    """Retrieval drafts (whole actions from the datastore) verified every step, drafter SD for
    the rest of each action."""
    acceptance: str = _setting("token_relaxed", "Drafter trees: acceptance rule (strict: every rule lossless, "
                               "verify-skip off, unless given).", TOKEN_RULES)
    relax_bins: int = _setting(9, "token_relaxed: accept a draft within this many bins of the target's choice "
                               "(strict acceptance: 0 unless given).")
    mode: str = _setting("retrieval", "hybrid (kinematic boundary) or one mode at every step.", hybrid.MODES)
    retrieval_acceptance: str = _setting("token_relaxed", "Acceptance rule for retrieval drafts (strict "
                                         "acceptance: strict unless given).", ACTION_RULES)
    retrieval_relax_bins: int = _setting(_HYB.relax_bins, "token_relaxed retrieval acceptance: bins.")
    n_candidates: int = _setting(_HYB.n_candidates, "Retrieved actions verified per step (0: no datastore "
                                 "query, the recent actions alone, verify-skip off unless given).")
    recent_candidates: int = _setting(_HYB.recent_candidates, "The env's own last executed actions verified as "
                                      "further candidates each retrieval step (our design).")
    max_dist: float = _setting(_HYB.max_dist, "Candidates with a squared key distance above this are invalid.")
    verify: str = _setting(_HYB.verify, "Retrieval drafts verified inside the prefill or in a second pass.",
                           hybrid.VERIFY)
    continuation: str = _setting(_HYB.continuation, "budget=fixed: what decodes the rest of an action after the "
                                 "prefill and its accepted candidate prefix: drafter rounds or single-token AR "
                                 "passes (no drafter).", hybrid.CONTINUATION)
    skip: bool = _setting(False, "Verify-skip: a confident retrieval-mode row executes its top candidate without "
                          "a target pass.")
    skip_source: str = _setting(_SKIP.source, "Verify-skip: what a skipped step executes: the datastore's top "
                                "candidate (retrieval) or the env's last action again (recent).", SKIP_SOURCES)
    n_confirm: int = _setting(_SKIP.n_confirm, "Verify-skip from recent actions: the last this many verified "
                              "steps each accepted their previous action whole.")
    k_skip: int = _setting(_SKIP.k_skip, "Verify-skip: at most this many consecutive skipped target passes.")
    skip_max_metric: float = _setting(_SKIP.max_metric, "Verify-skip only where the kinematic metric M is at most "
                                      "this (coarse motion; inf: wherever the row is in retrieval mode).")
    skip_eps: Optional[float] = _setting(None, "Verify-skip: nearest-key squared distance under which retrieval "
                                         f"is trusted (default: the datastore's calibration, else {_SKIP.eps}).")
    r_agree: int = _setting(_SKIP.r_agree, "Verify-skip: the top candidates agree within this many bins.")
    r_max: int = _setting(_SEQ.r_max, "seq_relaxed: no token further than this many bins from the target's.")
    r_seq: int = _setting(_SEQ.r_seq, "seq_relaxed: bound on the cumulative bin distance of the accepted prefix.")
    tau_on: Optional[float] = _setting(None, "Boundary: metric above which the drafter mode starts (default: the "
                                       "datastore's calibration).")
    tau_off: Optional[float] = _setting(None, "Boundary: metric below which the retrieval mode starts (default: "
                                        "the datastore's calibration).")
    min_dwell: Optional[int] = _setting(None, "Boundary: control steps a mode holds at least (default: the "
                                        "datastore's calibration).")
    budget: str = _setting("fixed", "Draft budget chosen per step from measured costs (auto) or the one fixed "
                           "tree (fixed).", BUDGETS)
    budget_trees: str = _setting("", "budget=auto: draft trees to choose from besides AR, TOPKxDEPTHxTOTAL "
                                 "separated by '/' (default: the top_k/depth/total_tokens tree if given, else "
                                 f"{_DEFAULT_TREES}).")
    budget_forget: float = _setting(_BUDGET.forget, "budget=auto: per unchosen step, share by which an "
                                    "option's estimate returns to its long-run mean (0: never).")
    budget_margin: float = _setting(_BUDGET.margin, "budget=auto: a drafting option must be predicted "
                                    "this much faster than AR to be chosen.")
    budget_max_batch: int = _setting(_BUDGET.max_batch, "budget=auto: the largest batch size (rows per device) at "
                                     "which drafting options run; above it the method decodes as plain AR.")
    row_buckets: int = _setting(_HYB.row_buckets, "Rows that need a target pass (not skipped) run gathered in the "
                                "smallest of this many batch fractions that holds them (1: always the whole batch; "
                                "k > 1 compiles the decode k times).")


@dataclasses.dataclass(frozen=True)
class HeiSDSettings(RetrievalSettings):
    """HeiSD: the kinematic boundary picks retrieval or drafter drafts per step; verify-skip,
    sequence-wise relaxed acceptance, and a draft budget chosen from measured costs."""
    mode: str = _setting("hybrid", "hybrid (kinematic boundary) or one mode at every step.", hybrid.MODES)
    retrieval_acceptance: str = _setting("seq_relaxed", "Acceptance rule for retrieval drafts (strict acceptance: "
                                         "strict unless given).", ACTION_RULES)
    recent_candidates: int = _setting(4, "The env's own last executed actions verified as further candidates "
                                      "each retrieval step (our design).")
    skip: bool = _setting(True, "Verify-skip: a confident retrieval-mode row executes a candidate without a target "
                          "pass (off with strict acceptance, or without the candidates its source needs, unless "
                          "given).")
    skip_source: str = _setting("recent", "Verify-skip: what a skipped step executes: the env's last action again "
                                "(recent), or the datastore's top candidate (retrieval, the paper's; rarely confident "
                                "enough to fire on the shipped stack).", SKIP_SOURCES)
    n_confirm: int = _setting(1, "Verify-skip from recent actions: the last this many verified steps each accepted "
                              "their previous action whole.")
    k_skip: int = _setting(2, "Verify-skip: at most this many consecutive skipped target passes (longer runs of "
                           "repeated actions cost closed-loop success).")
    r_max: int = _setting(9, "seq_relaxed: no token further than this many bins from the target's (the paper's 15 "
                          "costs closed-loop success on our suites).")
    r_seq: int = _setting(24, "seq_relaxed: bound on the cumulative bin distance of the accepted prefix (the "
                          "paper: 42).")
    budget: str = _setting("auto", "Draft budget chosen per step from measured costs (auto) or the one fixed tree "
                           "(fixed).", BUDGETS)


def setting_types(settings_cls: type) -> dict[str, type]:
    """Field name -> its Python type (int, float, bool, str; Optional[X] -> X)."""
    hints = typing.get_type_hints(settings_cls)
    out = {}
    for f in dataclasses.fields(settings_cls):
        kind = hints[f.name]
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        out[f.name] = args[0] if args else kind
    return out


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


def check_settings(name: str, settings: dict) -> dict:
    """A method's given settings, typed and validated against its settings record (a clear
    error naming the valid keys and values), before anything loads or compiles."""
    method = get(name)
    types = setting_types(method.settings) if method.settings else {}
    unknown = sorted(set(settings) - set(types))
    if unknown:
        raise ValueError(f"method {name!r}: unknown settings {unknown}; valid: {', '.join(types) or 'none'}")
    out = {k: _cast(k, v, types[k]) for k, v in settings.items()}
    for f in dataclasses.fields(method.settings) if method.settings else ():
        choices = f.metadata.get("choices")
        if f.name in out and choices and out[f.name] not in choices:
            raise ValueError(f"unknown {f.name} {out[f.name]!r}; valid: {', '.join(choices)}")
    if name == "expert":
        expert.ExpertConfig(**out)
    elif name == "drafter":
        drafter_spec(out)
    elif get(name).budget:
        hybrid_config(name, out)
    return out


def drafter_spec(given: dict) -> spec_decode.SpecConfig:
    """The drafter method's tree settings over its defaults."""
    s = {**dataclasses.asdict(DrafterSettings()), **given}
    return spec_decode.SpecConfig(**{k: s[k] for k in ("top_k", "depth", "total_tokens", "acceptance", "relax_bins")})


def hybrid_config(name: str, given: dict, calibration: dict | None = None) -> hybrid.HybridConfig:
    """The HybridConfig of method `name` (retrieval, heisd) from its given settings over the
    method's defaults and the datastore's calibration (metric scales, thresholds)."""
    s = {**dataclasses.asdict(get(name).settings()), **given}
    if s["acceptance"] == "strict":  # lossless unless asked otherwise
        for key, value in (("relax_bins", 0), ("retrieval_acceptance", "strict"), ("skip", False)):
            if key not in given:
                s[key] = value
    if "skip" not in given and ((s["n_candidates"] == 0 and s["skip_source"] == "retrieval")
                                or (s["recent_candidates"] == 0 and s["skip_source"] == "recent")):
        s["skip"] = False  # verify-skip needs its source's candidates: the datastore's, or the recent actions
    cal = calibration or {}
    spec = spec_decode.SpecConfig(**{k: s[k] for k in ("top_k", "depth", "total_tokens", "acceptance", "relax_bins")})
    skip = acceptance.SkipConfig(enabled=s["skip"], source=s["skip_source"], n_confirm=s["n_confirm"],
                                 k_skip=s["k_skip"], r_agree=s["r_agree"], max_metric=s["skip_max_metric"],
                                 eps=s["skip_eps"] if s["skip_eps"] is not None else cal.get("skip_eps", _SKIP.eps))
    metric = kinematics.MetricConfig(scales=tuple(cal.get("metric_scales", kinematics.MetricConfig().scales)))
    bd = {**cal.get("boundary", {}), **{k: s[k] for k in ("tau_on", "tau_off", "min_dwell") if s[k] is not None}}
    return hybrid.HybridConfig(
        spec=spec, mode=s["mode"], acceptance=s["retrieval_acceptance"], relax_bins=s["retrieval_relax_bins"],
        seq=acceptance.SeqRelaxedConfig(r_max=s["r_max"], r_seq=s["r_seq"]),
        n_candidates=s["n_candidates"], recent_candidates=s["recent_candidates"], max_dist=s["max_dist"],
        verify=s["verify"], continuation=s["continuation"], skip=skip, metric=metric, row_buckets=s["row_buckets"],
        boundary=kinematics.BoundaryConfig(**bd), budget=budget_config(s, given))


def budget_config(s: dict, given: dict) -> budget.BudgetConfig:
    """budget=auto chooses per step among AR and the trees of `budget_trees` (default: the
    tree given by top_k/depth/total_tokens if any, else budget.DEFAULT_TREES)."""
    mode = s["budget"]
    if mode == "auto" and "continuation" in given:
        raise ValueError("continuation is only used with budget=fixed (budget=auto chooses per step between AR after "
                         "the verified candidates, option ar+retrieval, and the drafter trees)")
    if mode != "auto":
        for key in ("budget_trees", "budget_forget", "budget_margin", "budget_max_batch"):
            if key in given:
                raise ValueError(f"{key} is only used with budget=auto")
        return budget.BudgetConfig(mode=mode)
    if s["budget_trees"]:
        trees = budget.parse_trees(s["budget_trees"])
    elif any(k in given for k in ("top_k", "depth", "total_tokens")):
        sp = spec_decode.SpecConfig(top_k=s["top_k"], depth=s["depth"], total_tokens=s["total_tokens"])
        trees = ((sp.top_k, sp.depth, sp.total_tokens),)
    else:
        trees = budget.DEFAULT_TREES
    return budget.BudgetConfig(mode="auto", trees=trees, forget=s["budget_forget"], margin=s["budget_margin"],
                               max_batch=s["budget_max_batch"])


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
    return expert.policy(env, expert.ExpertConfig(**given))


def _build_ar(env: TabletopEnv, paths: dict, given: dict, **_) -> Policy:
    params, cfg, tok = _load_target(env, paths["checkpoint"])
    cfg, params = in_numerics(cfg, ARSettings(**given), params)
    return vla_policy.decoding_policy("ar", params, cfg, tok, vla_policy.ar)


def _build_drafter(env: TabletopEnv, paths: dict, given: dict, **_) -> Policy:
    spec = drafter_spec(given)
    params, cfg, tok = _load_target(env, paths["checkpoint"])
    spec.check_fits(cfg)
    dparams, _ = checkpoint.load_drafter(paths["drafter"], cfg, params)
    cfg, params, dparams = in_numerics(cfg, DrafterSettings(**given), params, dparams)
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
    hcfg = hybrid_config(name, given, load_calibration(paths["datastore"], meta))
    hcfg.check_fits(cfg)
    cfg, params, dparams = in_numerics(cfg, get(name).settings(**given), params, dparams)
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
                    f"plain AR")
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
    settings: type  # its settings dataclass: flags, sweep keys and defaults
    loads: tuple[str, ...]  # what it reads: "checkpoint" (target VLA), "drafter", "datastore"
    renders: bool  # looks at the camera image (the expert does not: render off, faster)
    budget: bool  # may choose its draft budget from measured costs (takes batch_size, cost tables)
    build: Callable[..., Policy]  # (env, paths, given settings, **budget options) -> Policy


DEFAULT_PATHS = {"checkpoint": vla_policy.DEFAULT_CHECKPOINT, "drafter": vla_policy.DEFAULT_DRAFTER,
                 "datastore": vla_policy.DEFAULT_DATASTORE}
METHODS: dict[str, Method] = {m.name: m for m in (
    Method("expert", expert.ExpertConfig, (), renders=False, budget=False, build=_build_expert),
    Method("ar", ARSettings, ("checkpoint",), renders=True, budget=False, build=_build_ar),
    Method("drafter", DrafterSettings, ("checkpoint", "drafter"), renders=True, budget=False, build=_build_drafter),
    Method("retrieval", RetrievalSettings, ("checkpoint", "drafter", "datastore"), renders=True, budget=True,
           build=_build_hybrid("retrieval")),
    Method("heisd", HeiSDSettings, ("checkpoint", "drafter", "datastore"), renders=True, budget=True,
           build=_build_hybrid("heisd")),
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
    settings record's fields). batch_size (rows per device), cost_cache and calibrate_costs
    (measure a missing decode-cost table now instead of failing) reach the methods with a
    draft budget."""
    method = get(name)
    given = check_settings(name, settings)
    paths = {"checkpoint": checkpoint, "drafter": drafter, "datastore": datastore}
    paths = {k: Path(paths[k] if paths[k] is not None else DEFAULT_PATHS[k]) for k in method.loads}
    return method.build(env, paths, given, batch_size=batch_size, cost_cache=cost_cache,
                        calibrate_costs=calibrate_costs, log=log)


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
