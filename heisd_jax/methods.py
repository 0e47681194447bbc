"""Decoding methods registered by name, so the evaluator and sweeps can say --method=NAME.

Each entry builds an `envs.rollout.Policy` for an environment: the scripted expert (an
upper bound, no model) or a VLA decoding method over a policy checkpoint. The speculative
methods (drafter, retrieval, heisd) register here as they land.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs import camera, expert, language, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from envs.rollout import Policy
from heisd_jax import (acceptance, budget, checkpoint, cost_model, hybrid, kinematics, retrieval, spec_decode, vla,
                       vla_policy)

DTYPES = ("float32", "bfloat16")


def _load_target(env: TabletopEnv, checkpoint_path: str | Path):
    params, cfg, tok, _ = checkpoint.load_policy(checkpoint_path, text_vocab=language.VOCAB)
    if cfg.image_shape != env.config.camera.image_shape:
        raise ValueError(f"checkpoint {checkpoint_path} expects images of shape {cfg.image_shape} "
                         f"({cfg.n_views} view(s)), the env renders {env.config.camera.image_shape}")
    return params, cfg, tok


def in_dtype(cfg: vla.VLAConfig, dtype: str, *params):
    """The model config and parameter trees in compute dtype `dtype` (float32, bfloat16):
    parameters and KV caches are stored in it. Call after loading (fingerprints, which tie
    drafters and datastores to a target, are of the stored float32 parameters)."""
    if dtype not in DTYPES:
        raise ValueError(f"unknown dtype {dtype!r}; valid: {', '.join(DTYPES)}")
    cast = lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x  # noqa: E731
    return (vla.VLAConfig(**{**cfg.__dict__, "dtype": dtype}), *(jax.tree.map(cast, p) for p in params))


def _vla_method(name: str, decode: vla_policy.DecodeFn) -> Callable[..., Policy]:
    def make(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT,
             dtype: str = "float32") -> Policy:
        params, cfg, tok = _load_target(env, checkpoint_path)
        cfg, params = in_dtype(cfg, dtype, params)
        return vla_policy.decoding_policy(name, params, cfg, tok, decode)
    return make


def _drafter_method(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT,
                    drafter_path: str | Path = vla_policy.DEFAULT_DRAFTER, dtype: str = "float32",
                    **spec_settings) -> Policy:
    """Spec-VLA: EAGLE-2 tree drafts from the drafter, verified by the target."""
    spec = spec_decode.SpecConfig(**spec_settings)
    params, cfg, tok = _load_target(env, checkpoint_path)
    spec.check_fits(cfg)
    dparams, _ = checkpoint.load_drafter(drafter_path, cfg, params)
    cfg, params, dparams = in_dtype(cfg, dtype, params, dparams)
    return vla_policy.decoding_policy("drafter", {"target": params, "drafter": dparams}, cfg, tok,
                                      vla_policy.drafter_sd(spec), spec=spec)


COMMON_SETTINGS = {"dtype": str}  # every VLA method
SPEC_SETTINGS = {"top_k": int, "depth": int, "total_tokens": int, "acceptance": str, "relax_bins": int}
HYBRID_SETTINGS = {"mode": str, "retrieval_acceptance": str, "retrieval_relax_bins": int, "n_candidates": int,
                   "recent_candidates": int,
                   "max_dist": float, "verify": str, "continuation": str, "skip": bool, "k_skip": int, "skip_eps": float, "r_agree": int,
                   "r_max": int, "r_seq": int, "tau_on": float, "tau_off": float, "min_dwell": int,
                   "budget": str, "budget_trees": str, "budget_forget": float,
                   "budget_margin": float}
# Method defaults (HEISD.md): `retrieval` verifies retrieval drafts every step with Spec-VLA's
# token-wise rule; `heisd` adds the kinematic boundary, verify-skip and sequence-wise acceptance,
# and chooses its draft budget per step from measured costs (budget=auto).
HYBRID_DEFAULTS = {
    "retrieval": {"mode": "retrieval", "retrieval_acceptance": "token_relaxed", "skip": False,
                  "acceptance": "token_relaxed", "relax_bins": 9, "budget": "fixed"},
    "heisd": {"mode": "hybrid", "retrieval_acceptance": "seq_relaxed", "skip": True,
              "acceptance": "token_relaxed", "relax_bins": 9, "budget": "auto", "recent_candidates": 4},
}
BOUNDARY_FILE = "boundary.json"  # written into the datastore directory by experiments.calibrate_boundary


def _cast(key: str, value, kind):
    if kind is bool and isinstance(value, str):
        if value.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"setting {key}={value!r} is not a boolean (true/false)")
        return value.lower() in ("true", "1")
    try:
        return kind(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"setting {key}={value!r} is not a {kind.__name__}") from e


def check_settings(name: str, settings: dict) -> dict:
    """A method's settings, typed and validated (a clear error naming the valid keys and
    values), before anything loads or compiles."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    if name == "expert":
        return dict(settings)
    valid = {"drafter": SPEC_SETTINGS, "retrieval": {**SPEC_SETTINGS, **HYBRID_SETTINGS},
             "heisd": {**SPEC_SETTINGS, **HYBRID_SETTINGS}}.get(name, {})
    valid = {**COMMON_SETTINGS, **valid}
    unknown = sorted(set(settings) - set(valid))
    if unknown:
        raise ValueError(f"method {name!r}: unknown settings {unknown}; valid: {', '.join(valid)}")
    out = {k: _cast(k, v, valid[k]) for k, v in settings.items()}
    if out.get("dtype", "float32") not in DTYPES:
        raise ValueError(f"unknown dtype {out['dtype']!r}; valid: {', '.join(DTYPES)}")
    if name == "drafter":
        spec_decode.SpecConfig(**{k: v for k, v in out.items() if k in SPEC_SETTINGS})
    elif name in HYBRID_DEFAULTS:
        hybrid_config(name, out)
    return out


def hybrid_config(name: str, settings: dict, calibration: dict | None = None) -> hybrid.HybridConfig:
    """The HybridConfig of method `name` (retrieval, heisd) from flat settings over the
    method's defaults and the datastore's calibration (metric scales, thresholds)."""
    s = {**HYBRID_DEFAULTS[name], **settings}
    if s["acceptance"] == "strict":  # lossless unless asked otherwise
        for key, value in (("relax_bins", 0), ("retrieval_acceptance", "strict"), ("skip", False)):
            if key not in settings:
                s[key] = value
    if s.get("n_candidates") == 0 and "skip" not in settings:  # verify-skip needs the datastore's candidates
        s["skip"] = False
    cal = calibration or {}
    spec = spec_decode.SpecConfig(**{k: s[k] for k in SPEC_SETTINGS if k in s})
    seq = acceptance.SeqRelaxedConfig(**{k: s[k] for k in ("r_max", "r_seq") if k in s})
    skip_defaults = acceptance.SkipConfig()
    skip = acceptance.SkipConfig(enabled=s["skip"], k_skip=s.get("k_skip", skip_defaults.k_skip),
                                 eps=s.get("skip_eps", cal.get("skip_eps", skip_defaults.eps)),
                                 r_agree=s.get("r_agree", skip_defaults.r_agree))
    metric = kinematics.MetricConfig(scales=tuple(cal.get("metric_scales", kinematics.MetricConfig().scales)))
    bd = {**cal.get("boundary", {}), **{k: s[k] for k in ("tau_on", "tau_off", "min_dwell") if k in s}}
    return hybrid.HybridConfig(
        spec=spec, mode=s["mode"], acceptance=s["retrieval_acceptance"],
        relax_bins=s.get("retrieval_relax_bins", 9), seq=seq,
        n_candidates=s.get("n_candidates", 4), recent_candidates=s.get("recent_candidates", 0),
        max_dist=s.get("max_dist", float("inf")),
        verify=s.get("verify", "prefill"), continuation=s.get("continuation", "drafter"), skip=skip, metric=metric,
        boundary=kinematics.BoundaryConfig(**bd),
        budget=budget_config(s, settings))


def budget_config(s: dict, given: dict) -> budget.BudgetConfig:
    """budget=auto chooses per step among AR and the trees of `budget_trees` (default: the
    tree given by top_k/depth/total_tokens if any, else budget.DEFAULT_TREES)."""
    mode = s.get("budget", "fixed")
    if mode == "auto" and "continuation" in given:
        raise ValueError("continuation is only used with budget=fixed (budget=auto chooses per step between AR after "
                         "the verified candidates, option ar+retrieval, and the drafter trees)")
    if mode != "auto":
        for key in ("budget_trees", "budget_forget", "budget_margin"):
            if key in given:
                raise ValueError(f"{key} is only used with budget=auto")
        return budget.BudgetConfig(mode=mode)
    if "budget_trees" in s:
        trees = budget.parse_trees(s["budget_trees"])
    elif any(k in given for k in ("top_k", "depth", "total_tokens")):
        sp = spec_decode.SpecConfig(**{k: s[k] for k in ("top_k", "depth", "total_tokens") if k in s})
        trees = ((sp.top_k, sp.depth, sp.total_tokens),)
    else:
        trees = budget.DEFAULT_TREES
    return budget.BudgetConfig(mode="auto", trees=trees, forget=s.get("budget_forget", budget.BudgetConfig.forget),
                               margin=s.get("budget_margin", budget.BudgetConfig.margin))


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


def _hybrid_method(name: str):
    def make(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT,
             drafter_path: str | Path = vla_policy.DEFAULT_DRAFTER,
             datastore_path: str | Path = vla_policy.DEFAULT_DATASTORE, batch_size: int | None = None,
             cost_cache: str | Path | None = cost_model.DEFAULT_CACHE, calibrate_costs: bool = False,
             log: Callable[[str], None] = print, **settings) -> Policy:
        """batch_size: rows per device of the decode step. budget=auto loads the decode-cost
        table for that size from `cost_cache`; where none is cached it fails, unless
        `calibrate_costs` asks to measure it now (then cached; cost_cache None: never cached)."""
        settings = check_settings(name, settings)
        dtype = settings.pop("dtype", "float32")
        params, cfg, tok = _load_target(env, checkpoint_path)
        dparams, _ = checkpoint.load_drafter(drafter_path, cfg, params)
        store, key_spec, meta = retrieval.load(datastore_path, tok, checkpoint.fingerprint(params))
        missing = sorted(set(env.global_index.tolist()) - set(np.unique(np.asarray(store.task)).tolist()))
        if missing:
            raise ValueError(f"datastore {datastore_path} has no entries for tasks "
                             f"{[tasks_lib.ALL_TASKS[i].name for i in missing]}; rebuild it from demos of those tasks")
        hcfg = hybrid_config(name, settings, load_calibration(datastore_path, meta))
        hcfg.check_fits(cfg)
        cfg, params, dparams = in_dtype(cfg, dtype, params, dparams)
        all_params = {"target": params, "drafter": dparams, "store": store}
        table = None
        if hcfg.budget.mode == "auto":
            if batch_size is None or batch_size < 1:
                raise ValueError(f"budget=auto measures decode costs at the batch size in use: pass batch_size "
                                 f"(rows per device), got {batch_size}")
            table = cost_model.load_or_calibrate(all_params, cfg, hcfg, batch_size, cost_cache, log,
                                                  measure=calibrate_costs)
            all_params["costs"] = table.costs()
        policy = vla_policy.hybrid_policy(name, all_params, cfg, tok, hcfg, key_spec, env.global_index)
        return dataclasses.replace(policy, meta=dict(policy.meta, cost_table=table))
    make.__doc__ = f"`{name}`: retrieval drafts (datastore) and drafter SD (see heisd_jax.hybrid)."
    return make


METHODS: dict[str, Callable[..., Policy]] = {
    "expert": lambda env, **kw: expert.policy(env, expert.ExpertConfig(**kw)),
    "ar": _vla_method("ar", vla_policy.ar),
    "drafter": _drafter_method,
    "retrieval": _hybrid_method("retrieval"),
    "heisd": _hybrid_method("heisd"),
}
USES_CAMERA = {"expert": False}  # methods that never look at the image (render off: faster)


def env_config(name: str, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT) -> EnvConfig:
    """The env settings method `name` runs under: the camera views and size its checkpoint
    was trained on (read from the checkpoint's metadata), no rendering for the expert."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    if not USES_CAMERA.get(name, True):
        return EnvConfig(render=False)
    cfg = checkpoint.read_config(checkpoint_path)
    if cfg.n_views > len(camera.VIEWS):
        raise ValueError(f"checkpoint {checkpoint_path} expects {cfg.n_views} views; the env has {camera.VIEWS}")
    return EnvConfig(camera=camera.CameraConfig(height=cfg.image_size, width=cfg.image_size, wrist=cfg.n_views > 1))


CHECKPOINTS = {"ar": ("checkpoint_path",), "drafter": ("checkpoint_path", "drafter_path"),
               "retrieval": ("checkpoint_path", "drafter_path", "datastore_path"),
               "heisd": ("checkpoint_path", "drafter_path", "datastore_path")}  # what each method loads


def make_policy(name: str, env: TabletopEnv, *, checkpoint: str | Path | None = None,
                drafter: str | Path | None = None, datastore: str | Path | None = None,
                batch_size: int | None = None, cost_cache: str | Path | None = cost_model.DEFAULT_CACHE,
                calibrate_costs: bool = False, **settings) -> Policy:
    """The policy of method `name`; `checkpoint`/`drafter`/`datastore` (default: the shipped
    ones) reach only the methods that load them, `settings` are the method's own options;
    batch_size (rows per device), cost_cache and calibrate_costs (measure a missing
    decode-cost table now instead of failing) reach the methods with a draft budget."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    given = {"checkpoint_path": checkpoint, "drafter_path": drafter, "datastore_path": datastore}
    paths = {k: given[k] for k in CHECKPOINTS.get(name, ()) if given[k] is not None}
    if name in HYBRID_DEFAULTS:
        paths.update(batch_size=batch_size, cost_cache=cost_cache, calibrate_costs=calibrate_costs)
    return METHODS[name](env, **paths, **settings)


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
