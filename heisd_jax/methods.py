"""Decoding methods registered by name, so the evaluator and sweeps can say --method=NAME.

Each entry builds an `envs.rollout.Policy` for an environment: the scripted expert (an
upper bound, no model) or a VLA decoding method over a policy checkpoint. The speculative
methods (drafter, retrieval, heisd) register here as they land.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from envs import expert
from envs.env import TabletopEnv
from envs.rollout import Policy
from heisd_jax import checkpoint, spec_decode, vla_policy


def _load_target(env: TabletopEnv, checkpoint_path: str | Path):
    params, cfg, tok, _ = checkpoint.load_policy(checkpoint_path)
    if cfg.image_size != env.config.camera.width or cfg.image_size != env.config.camera.height:
        raise ValueError(f"checkpoint {checkpoint_path} expects {cfg.image_size}px images, the env renders "
                         f"{env.config.camera.width}x{env.config.camera.height}")
    return params, cfg, tok


def _vla_method(name: str, decode: vla_policy.DecodeFn) -> Callable[..., Policy]:
    def make(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT) -> Policy:
        return vla_policy.decoding_policy(name, *_load_target(env, checkpoint_path), decode)
    return make


def _drafter_method(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT,
                    drafter_path: str | Path = vla_policy.DEFAULT_DRAFTER, **spec_settings) -> Policy:
    """Spec-VLA: EAGLE-2 tree drafts from the drafter, verified by the target."""
    spec = spec_decode.SpecConfig(**spec_settings)
    params, cfg, tok = _load_target(env, checkpoint_path)
    spec.check_fits(cfg)
    dparams, _ = checkpoint.load_drafter(drafter_path, cfg, params)
    return vla_policy.decoding_policy("drafter", {"target": params, "drafter": dparams}, cfg, tok,
                                      vla_policy.drafter_sd(spec))


METHODS: dict[str, Callable[..., Policy]] = {
    "expert": lambda env, **kw: expert.policy(env, expert.ExpertConfig(**kw)),
    "ar": _vla_method("ar", vla_policy.ar),
    "drafter": _drafter_method,
}
USES_CAMERA = {"expert": False}  # methods that never look at the image (render off: faster)


CHECKPOINTS = {"ar": ("checkpoint_path",), "drafter": ("checkpoint_path", "drafter_path")}  # what each method loads


def make_policy(name: str, env: TabletopEnv, *, checkpoint: str | Path | None = None,
                drafter: str | Path | None = None, **settings) -> Policy:
    """The policy of method `name`; `checkpoint`/`drafter` (default: the shipped ones) reach
    only the methods that load them, `settings` are the method's own options."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    given = {"checkpoint_path": checkpoint, "drafter_path": drafter}
    paths = {k: given[k] for k in CHECKPOINTS.get(name, ()) if given[k] is not None}
    return METHODS[name](env, **paths, **settings)
