"""Decoding methods registered by name, so the evaluator and sweeps can say --method=NAME.

Each entry builds an `envs.rollout.Policy` for an environment. Only the scripted expert
exists so far; the VLA decoding methods (ar, drafter, retrieval, heisd) register here.
"""

from __future__ import annotations

from typing import Callable

from envs import expert
from envs.env import TabletopEnv
from envs.rollout import Policy

METHODS: dict[str, Callable[..., Policy]] = {
    "expert": lambda env, **kw: expert.policy(env, expert.ExpertConfig(**kw)),
}


def make_policy(name: str, env: TabletopEnv, **settings) -> Policy:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    return METHODS[name](env, **settings)
