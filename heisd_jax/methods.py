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


def _vla_method(name: str, decode: vla_policy.DecodeFn) -> Callable[..., Policy]:
    def make(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT) -> Policy:
        params, cfg, tok, _ = checkpoint.load_policy(checkpoint_path)
        if cfg.image_size != env.config.camera.width or cfg.image_size != env.config.camera.height:
            raise ValueError(f"checkpoint {checkpoint_path} expects {cfg.image_size}px images, the env renders "
                             f"{env.config.camera.width}x{env.config.camera.height}")
        return vla_policy.decoding_policy(name, params, cfg, tok, decode)
    return make


def _drafter_method(env: TabletopEnv, checkpoint_path: str | Path = vla_policy.DEFAULT_CHECKPOINT,
                    drafter_path: str | Path = vla_policy.DEFAULT_DRAFTER, **spec_settings) -> Policy:
    """Spec-VLA: EAGLE-2 tree drafts from the drafter, verified by the target."""
    spec = spec_decode.SpecConfig(**spec_settings)
    params, cfg, tok, _ = checkpoint.load_policy(checkpoint_path)
    spec.check_fits(cfg)
    dparams, _ = checkpoint.load_drafter(drafter_path, cfg, params)
    decode = vla_policy.drafter_sd(spec)
    return vla_policy.decoding_policy("drafter", {"target": params, "drafter": dparams}, cfg, tok, decode)


METHODS: dict[str, Callable[..., Policy]] = {
    "expert": lambda env, **kw: expert.policy(env, expert.ExpertConfig(**kw)),
    "ar": _vla_method("ar", vla_policy.ar),
    "drafter": _drafter_method,
}
USES_CAMERA = {"expert": False}  # methods that never look at the image (render off: faster)


def make_policy(name: str, env: TabletopEnv, **settings) -> Policy:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    return METHODS[name](env, **settings)
