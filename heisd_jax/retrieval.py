"""The retrieval datastore at run time (REST-style; HeiSD's use: our design): its types,
the query keys, the kNN query and loading. Building one offline is
`heisd_jax.harness.offline.datastore` (`python -m experiments.build_datastore`).

Keys describe where the robot is in a task: the last `history` actions (normalised to
[-1, 1] by the target's tokenizer; zeros before the episode start), the end-effector
position (scaled, `pos_scale` per metre), its quaternion and jaw opening, i.e. the proprio
vector; values are the 7 tokens of the action taken next, tokenized by the target's
tokenizer. Entries carry their task (global task index): a query only matches its own task.

`query` is exact k-nearest neighbours on device: squared distances by one matmul,
`lax.top_k`, a static number of candidates with a validity mask (same task, within
`max_dist`). A datastore is one .npz + meta.json beside the checkpoints, tied to the
target's tokenizer and checkpoint fingerprint; `load` refuses one built for another target.
Keys are stored as float16 (half the size; a key's entries are O(1), so the rounding,
~1e-3 relative, is far below the distances that separate neighbours) and used as float32.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from heisd_jax.tokenizer import ACTION_DIM, ActionTokenizer

FORMAT = "heisd-jax-datastore-v2"  # v2: compressed, float16 keys, uint8 bins and task ids


@dataclasses.dataclass(frozen=True)
class KeySpec:
    history: int = 2  # previous actions in the key
    pos_scale: float = 10.0  # per metre: 1 cm of end-effector position weighs 0.1

    @property
    def dim(self) -> int:
        return self.history * ACTION_DIM + 8


@struct.dataclass
class Datastore:
    keys: jnp.ndarray  # [N, dim] float32
    sq_norms: jnp.ndarray  # [N] |key|^2
    tokens: jnp.ndarray  # [N, 7] int32 (action ids of the target's vocabulary)
    task: jnp.ndarray  # [N] int32 global task index

    @property
    def size(self) -> int:
        return self.tokens.shape[0]

    @classmethod
    def of(cls, keys, tokens, task) -> "Datastore":
        """A datastore of entries: keys [N, dim], value token ids [N, 7], global task indices [N]."""
        keys = jnp.asarray(keys, jnp.float32)
        return cls(keys=keys, sq_norms=(keys * keys).sum(-1), tokens=jnp.asarray(tokens, jnp.int32),
                   task=jnp.asarray(task, jnp.int32))


def make_keys(spec: KeySpec, tok: ActionTokenizer, prev_actions, proprio) -> jnp.ndarray:
    """Keys [..., dim] from the last `history` actions [..., history, 7] (oldest first; zeros
    where none) and the proprio vector [..., 8]."""
    prev = jnp.clip(tok.normalize(jnp.asarray(prev_actions, jnp.float32)), -1, 1)
    prev = prev.reshape(prev.shape[:-2] + (spec.history * ACTION_DIM,))
    proprio = jnp.asarray(proprio, jnp.float32)
    return jnp.concatenate([prev, proprio[..., :3] * spec.pos_scale, proprio[..., 3:]], -1)


def query(store: Datastore, keys: jnp.ndarray, task: jnp.ndarray, n: int, max_dist: float = jnp.inf):
    """Exact kNN within the query's task. keys [B, dim], task [B] -> (candidate tokens
    [B, n, 7], squared distances [B, n], valid [B, n])."""
    # Full float32 (not TF32), so near-equal neighbours rank alike at every batch size.
    cross = jnp.matmul(keys, store.keys.T, precision=jax.lax.Precision.HIGHEST)
    d2 = (keys * keys).sum(-1, keepdims=True) - 2.0 * cross + store.sq_norms[None]
    d2 = jnp.where(store.task[None] == task[:, None], jnp.maximum(d2, 0.0), jnp.inf)
    neg, idx = jax.lax.top_k(-d2, n)
    dist = -neg
    return store.tokens[idx], dist, jnp.isfinite(dist) & (dist <= max_dist)


def read_meta(path: str | os.PathLike) -> dict:
    """A datastore's meta.json (its build settings, tokenizer, metric scales), without its arrays."""
    try:
        return json.loads((Path(path) / "meta.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"no readable datastore at {path}: {e}") from e


def load(path: str | os.PathLike, tok: ActionTokenizer, target_fingerprint: str) -> tuple[Datastore, KeySpec, dict]:
    """(datastore, key spec, meta); refuses one built for another tokenizer or target."""
    path = Path(path)
    meta = read_meta(path)
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: format {meta.get('format')}, expected {FORMAT}")
    try:
        same_tok = ActionTokenizer.from_dict(meta["tokenizer"]) == tok
    except (KeyError, TypeError, ValueError):
        same_tok = False
    if not same_tok:
        raise ValueError(f"datastore {path} was built with another action tokenizer")
    if meta.get("target_fingerprint") != target_fingerprint:
        raise ValueError(f"datastore {path} was built for another target checkpoint "
                         f"({meta.get('target_fingerprint')} != {target_fingerprint})")
    try:
        with np.load(path / "datastore.npz") as z:
            keys, task = z["keys"].astype(np.float32), z["task"].astype(np.int32)
            tokens = z["bins"].astype(np.int32) + tok.first_action_id
    except Exception as e:  # truncated or damaged archive
        raise ValueError(f"datastore {path}: cannot read datastore.npz ({e})") from e
    spec = KeySpec(**meta["key_spec"])
    if keys.shape != (meta["size"], spec.dim) or tokens.shape != (meta["size"], ACTION_DIM):
        raise ValueError(f"datastore {path}: arrays {keys.shape}/{tokens.shape} do not match its metadata")
    return Datastore.of(keys, tokens, task), spec, meta
