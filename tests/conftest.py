"""Shared fixtures: one environment and its jitted functions per test session (compiling
MJX on CPU dominates test time, so every test reuses the same compiled batch shapes)."""

import envs  # noqa: F401  (sets XLA_FLAGS before JAX starts)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.env import EnvConfig, TabletopEnv

import tiny_models


class Compiled:
    """A physics-only env (all 40 tasks) with batched reset/step compiled once."""

    def __init__(self):
        self.env = TabletopEnv(config=EnvConfig(render=False))
        self.reset = jax.jit(jax.vmap(self.env.reset))
        self.step = jax.jit(jax.vmap(self.env.step))

    def start(self, task_ids, episodes=(0, 0)):
        task_ids = np.asarray(task_ids)
        keys = self.env.initial_state_keys(task_ids, np.asarray(episodes))
        return self.reset(keys, jnp.asarray(task_ids, jnp.int32))


@pytest.fixture(scope="session")
def compiled():
    return Compiled()


@pytest.fixture(scope="session")
def tiny_hybrid():
    """The hybrid/budget tests' models and batch: (params, observations, AR tokens)."""
    tp, dp = tiny_models.aligned_pair(0.35)
    obs = tiny_models.obs(7, batch=tiny_models.HYBRID_B)
    return {"target": tp, "drafter": dp}, obs, np.asarray(tiny_models.ar(tp, obs))
