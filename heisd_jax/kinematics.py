"""HeiSD's kinematic fused metric and the hybrid boundary (docs/method.md; the formula
is our design, following the paper's design card).

Features per env and control step, read from the MJX state's end-effector kinematics
(`EnvState.kin`): linear speed |v|, angular speed |w|, linear acceleration |a|, gripper
opening speed |g|, and turning 1 - cos(v_t, v_{t-1}) (0 while moving straight).
Fused metric `M = sum_j w_j f_j / s_j` with per-feature scales s_j measured on the demos:
high M = fine manipulation (slowing, turning, contact, gripper events) -> drafter mode; low
M = smooth transport -> retrieval mode. The boundary is a threshold with hysteresis
(tau_on > tau_off) and a minimum dwell in a mode.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
from flax import struct

FEATURES = ("speed", "ang_speed", "acc", "gripper_speed", "turning")
RETRIEVAL, DRAFTER = 0, 1


def features(lin_vel, ang_vel, lin_acc, gripper_vel, prev_lin_vel) -> jnp.ndarray:
    """[..., 5] kinematic features (see FEATURES). Turning is 0 when either velocity is ~0."""
    speed = jnp.linalg.norm(lin_vel, axis=-1)
    prev_speed = jnp.linalg.norm(prev_lin_vel, axis=-1)
    cos = (lin_vel * prev_lin_vel).sum(-1) / jnp.maximum(speed * prev_speed, 1e-9)
    moving = (speed > 1e-4) & (prev_speed > 1e-4)
    turning = jnp.where(moving, 1.0 - jnp.clip(cos, -1.0, 1.0), 0.0)
    return jnp.stack([speed, jnp.linalg.norm(ang_vel, axis=-1), jnp.linalg.norm(lin_acc, axis=-1),
                      jnp.abs(gripper_vel), turning], -1)


@dataclasses.dataclass(frozen=True)
class MetricConfig:
    scales: tuple[float, ...] = (1.0,) * 5  # per-feature scale (demos: see `scales_from_demos`)
    weights: tuple[float, ...] = (1.0,) * 5

    def __post_init__(self):
        if len(self.scales) != len(FEATURES) or len(self.weights) != len(FEATURES):
            raise ValueError(f"scales and weights need {len(FEATURES)} entries ({', '.join(FEATURES)})")
        if any(s <= 0 for s in self.scales) or any(w < 0 for w in self.weights):
            raise ValueError(f"scales must be > 0 and weights >= 0: {self}")


def fused_metric(f: jnp.ndarray, cfg: MetricConfig) -> jnp.ndarray:
    """M [...] from features [..., 5]."""
    return (f * jnp.asarray(cfg.weights) / jnp.asarray(cfg.scales)).sum(-1)


def scales_from_demos(f: np.ndarray, quantile: float = 0.9) -> tuple[float, ...]:
    """Per-feature scale: the `quantile` of each feature over demo steps (floored at 1e-6)."""
    return tuple(float(max(np.quantile(f[:, j], quantile), 1e-6)) for j in range(f.shape[1]))


@dataclasses.dataclass(frozen=True)
class BoundaryConfig:
    tau_on: float = 1.5  # M above this (held min_dwell steps in retrieval mode) -> drafter mode
    tau_off: float = 0.8  # M below this (after min_dwell steps in drafter mode) -> retrieval mode
    min_dwell: int = 3

    def __post_init__(self):
        if not self.tau_on > self.tau_off >= 0:
            raise ValueError(f"need tau_on > tau_off >= 0, got tau_on={self.tau_on}, tau_off={self.tau_off}")
        if self.min_dwell < 1:
            raise ValueError(f"min_dwell must be >= 1, got {self.min_dwell}")


@struct.dataclass
class BoundaryState:
    mode: jnp.ndarray  # [...] int32: RETRIEVAL or DRAFTER
    dwell: jnp.ndarray  # [...] int32: steps spent in the mode


def boundary_init(shape=(), mode: int = DRAFTER) -> BoundaryState:
    """Episodes start in drafter mode (the arm is about to act, not yet transporting)."""
    return BoundaryState(mode=jnp.full(shape, mode, jnp.int32), dwell=jnp.zeros(shape, jnp.int32))


def boundary_step(state: BoundaryState, metric: jnp.ndarray, cfg: BoundaryConfig) -> BoundaryState:
    """The mode for this step, from the metric and the hysteresis/dwell rule."""
    settled = state.dwell >= cfg.min_dwell
    to_drafter = (state.mode == RETRIEVAL) & (metric > cfg.tau_on) & settled
    to_retrieval = (state.mode == DRAFTER) & (metric < cfg.tau_off) & settled
    switch = to_drafter | to_retrieval
    mode = jnp.where(switch, 1 - state.mode, state.mode)
    return BoundaryState(mode=mode.astype(jnp.int32), dwell=jnp.where(switch, 0, state.dwell + 1).astype(jnp.int32))
