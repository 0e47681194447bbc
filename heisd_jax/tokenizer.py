"""OpenVLA's action tokenizer: 7 dimensions, each cut into 256 uniform bins.

Each motion dimension is first normalised to [-1, 1] with the training actions' 1st and
99th percentiles (clipped outside them); the gripper dimension is already in [-1, 1] and is
not renormalised (OpenVLA's normalisation mask). [-1, 1] is cut into N_BINS equal bins;
bin b maps onto vocabulary id `vocab_size - N_BINS + b`, a monotone map, so the distance
between two action token ids equals their bin distance. `to_ids` / `to_actions` are jittable.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

N_BINS = 256
INVALID_ID = -1  # the token id of a row whose observation was invalid (`vla.mark_invalid`)
ACTION_DIM = 7
NORMALIZE_MASK = np.array([True] * 6 + [False])  # the gripper is not renormalised


@dataclasses.dataclass(frozen=True)
class ActionTokenizer:
    q01: tuple[float, ...]  # [7] 1st percentile of the training actions
    q99: tuple[float, ...]  # [7] 99th percentile
    vocab_size: int  # the model's vocabulary; actions use its last N_BINS ids

    def __post_init__(self):
        if len(self.q01) != ACTION_DIM or len(self.q99) != ACTION_DIM:
            raise ValueError(f"tokenizer statistics need {ACTION_DIM} values per percentile")
        if not np.all(np.asarray(self.q99) > np.asarray(self.q01)):
            raise ValueError(f"q99 must exceed q01 in every dimension: {self.q01} / {self.q99}")
        if self.vocab_size < N_BINS:
            raise ValueError(f"vocab_size {self.vocab_size} < {N_BINS} action bins")

    @classmethod
    def fit(cls, actions: np.ndarray, vocab_size: int) -> "ActionTokenizer":
        """Statistics from training actions [N, 7]."""
        q01, q99 = np.percentile(actions, 1, axis=0), np.percentile(actions, 99, axis=0)
        q01 = np.where(NORMALIZE_MASK, q01, -1.0)
        q99 = np.where(NORMALIZE_MASK, np.maximum(q99, q01 + 1e-3), 1.0)
        return cls(tuple(map(float, q01)), tuple(map(float, q99)), vocab_size)

    @property
    def first_action_id(self) -> int:
        return self.vocab_size - N_BINS

    @property
    def bin_width(self) -> float:
        """Width of one bin in normalised units."""
        return 2.0 / N_BINS

    def normalize(self, action):
        q01, q99 = jnp.asarray(self.q01), jnp.asarray(self.q99)
        return jnp.clip(2.0 * (action - q01) / (q99 - q01) - 1.0, -1.0, 1.0)

    def unnormalize(self, x):
        q01, q99 = jnp.asarray(self.q01), jnp.asarray(self.q99)
        return (x + 1.0) / 2.0 * (q99 - q01) + q01

    def to_bins(self, action):
        """[..., 7] actions -> [..., 7] int32 bins in [0, N_BINS)."""
        x = self.normalize(action)
        return jnp.clip(jnp.floor((x + 1.0) / 2.0 * N_BINS), 0, N_BINS - 1).astype(jnp.int32)

    def from_bins(self, bins):
        """[..., 7] bins -> [..., 7] actions at the bin centres."""
        x = -1.0 + (bins.astype(jnp.float32) + 0.5) * self.bin_width
        return self.unnormalize(x)

    def to_ids(self, action):
        """[..., 7] actions -> [..., 7] vocabulary ids."""
        return self.to_bins(action) + self.first_action_id

    def to_actions(self, token_ids):
        """[..., 7] vocabulary ids -> [..., 7] actions (ids outside the action range clip).
        `INVALID_ID` gives 0.0, the zero action: no arm motion, the gripper half open,
        rather than the full-speed move of a clipped id."""
        actions = self.from_bins(jnp.clip(token_ids - self.first_action_id, 0, N_BINS - 1))
        return jnp.where(token_ids == INVALID_ID, 0.0, actions)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ActionTokenizer":
        return cls(tuple(d["q01"]), tuple(d["q99"]), int(d["vocab_size"]))
