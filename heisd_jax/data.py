"""Training data for the VLA: demonstration steps as (observation, action tokens) pairs.

The whole step table is loaded once into device memory (a demos dataset of the four suites
is a few GB of 64x64 images: it fits on one accelerator), and minibatches are drawn inside
the jitted train step by random indices, so the accelerator never waits on the host.
"""

from __future__ import annotations

import numpy as np
from flax import struct
import jax
import jax.numpy as jnp

from envs import demos, language
from heisd_jax import vla
from heisd_jax.tokenizer import ActionTokenizer


@struct.dataclass
class StepTable:
    image: jnp.ndarray  # [N, H, W, 3] uint8
    proprio: jnp.ndarray  # [N, 8]
    instruction: jnp.ndarray  # [N, L] int32
    action: jnp.ndarray  # [N, 7] float32

    @property
    def size(self) -> int:
        return self.action.shape[0]


def load_steps(path: str, episodes: list[int] | None = None) -> StepTable:
    """All steps of a demos dataset (or of the given episodes) as host arrays."""
    ds = demos.DemoDataset(path)
    idx = range(len(ds)) if episodes is None else episodes
    cols = {k: [] for k in ("image", "proprio", "action", "instruction")}
    for i in idx:
        ep = ds.episode(i)
        n = len(ep["action"])
        cols["image"].append(ep["image"])
        cols["proprio"].append(ep["proprio"])
        cols["action"].append(ep["action"])
        cols["instruction"].append(np.repeat(language.encode(ds.episodes[i]["instruction"])[None], n, 0))
    if not cols["action"]:
        raise ValueError(f"{path}: no episodes to load")
    return StepTable(*(np.concatenate(cols[k]) for k in ("image", "proprio", "instruction", "action")))


def split_episodes(path: str, holdout: float, seed: int = 0) -> tuple[list[int], list[int]]:
    """Episode indices for training and held-out evaluation (by episode, not by step)."""
    n = len(demos.DemoDataset(path))
    order = np.random.default_rng(seed).permutation(n)
    k = int(round(n * holdout))
    return sorted(order[k:].tolist()), sorted(order[:k].tolist())


def sample_batch(table: StepTable, key: jax.Array, batch: int, tok: ActionTokenizer):
    """A random minibatch: (vla.Observation, action token ids [B, 7])."""
    i = jax.random.randint(key, (batch,), 0, table.size)
    obs = vla.Observation(image=table.image[i], instruction=table.instruction[i], proprio=table.proprio[i])
    return obs, tok.encode(table.action[i])
