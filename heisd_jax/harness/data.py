"""Training data for the VLA: demonstration steps as (observation, action tokens) pairs.

The whole step table is loaded once into device memory (a demos dataset of the four suites
is a few GB of 64x64 images: it fits on one accelerator), and minibatches are drawn inside
the jitted train step by random indices, so the accelerator never waits on the host. The
draw is uniform over the rows, or, for a table loaded with task weights, in proportion to
each row's task's weight (a DAgger round's fine-tuning then sees most of the tasks its
policy fails, however small their share of the aggregate).
"""

from __future__ import annotations

from typing import Mapping, Sequence

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
    # Running sum of the rows' integer draw weights [N] int32, or None: every row alike.
    cumulative_weight: jnp.ndarray | None = None

    @property
    def size(self) -> int:
        return self.action.shape[0]


def load_steps(path: str, episodes: list[int] | None = None) -> StepTable:
    """All steps of a demos dataset (or of the given episodes) as host arrays."""
    return load_step_table([(path, episodes)])


def load_step_table(sources: Sequence[tuple[str, Sequence[int] | None]],
                    task_weights: Mapping[str, int] | None = None,
                    source_weights: Sequence[int] | None = None) -> StepTable:
    """The steps of several datasets' episodes ((path, episode indices or None for all), in
    order) as one host table. Each column is allocated once and filled episode by episode
    from the memory-mapped shards, so a table of N steps holds one copy of them in memory,
    not the episodes', the datasets' and their concatenation's (a build's last DAgger round
    trains on ~1.3M steps, ~31 GB of images).

    `task_weights` (task name -> a positive integer; tasks not named: 1) makes `draw_rows`
    draw each step in proportion to its episode's task's weight; `source_weights` (a positive
    integer per source) multiplies that by its source's, so that, say, the newest data is drawn
    several times as often as an aggregate of older rounds. Where every step's weight is 1 the
    table holds none, and draws as a table loaded without weights."""
    if source_weights is None:
        source_weights = [1] * len(sources)
    if len(source_weights) != len(sources) or not all(isinstance(n, (int, np.integer)) and n >= 1 for n in source_weights):
        raise ValueError(f"source weights must be one positive integer per dataset ({len(sources)}), got "
                         f"{list(source_weights)}")
    plan = []  # (dataset, episode index, its source's weight)
    for (path, episodes), n in zip(sources, source_weights):
        ds = demos.DemoDataset(path)
        plan += [(ds, i, n) for i in (range(len(ds)) if episodes is None else episodes)]
    if not plan:
        raise ValueError(f"{[str(p) for p, _ in sources]}: no episodes to load")
    shapes = {str(ds.path): ds.shard(ds.episodes[i]["shard"])["image"].shape[1:] for ds, i, _ in plan}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"the datasets hold images of different shapes: {shapes}")
    n = sum(ds.episodes[i]["length"] for ds, i, _ in plan)
    first = plan[0][0].shard(plan[0][0].episodes[plan[0][1]]["shard"])
    table = StepTable(**{f: np.empty((n, *first[f].shape[1:]), first[f].dtype) for f in ("image", "proprio", "action")},
                      instruction=np.empty((n, language.MAX_INSTRUCTION_TOKENS), np.int32))
    weights = task_weights or {}
    table = with_row_weights(table, np.concatenate([np.full(ds.episodes[i]["length"],
                                                            weights.get(ds.episodes[i]["task"], 1) * source)
                                                    for ds, i, source in plan]))
    row = 0
    for ds, i, _ in plan:
        e = ds.episodes[i]
        shard, rows = ds.shard(e["shard"]), slice(e["start"], e["start"] + e["length"])
        out = slice(row, row + e["length"])
        for field in ("image", "proprio", "action"):
            getattr(table, field)[out] = shard[field][rows]
        table.instruction[out] = language.to_ids(e["instruction"])
        row += e["length"]
    return table


def with_row_weights(table: StepTable, row_weight: np.ndarray) -> StepTable:
    """`table` drawn by `draw_rows` in proportion to `row_weight` ([N] positive integers): their
    running sum is stored, or nothing where every weight is 1 (the uniform draw). ValueError
    for a weight that is not a positive integer, or a total beyond int32."""
    row_weight = np.asarray(row_weight)
    if row_weight.shape != (table.size,) or not np.issubdtype(row_weight.dtype, np.integer) or np.any(row_weight < 1):
        raise ValueError(f"row weights must be positive integers, one per row of the table's {table.size}; "
                         f"got {row_weight.dtype} {row_weight.shape}, values {np.unique(row_weight)[:8]}")
    total = int(row_weight.sum(dtype=np.int64))
    if total >= 2**31:
        raise ValueError(f"the row weights sum to {total}: at most 2**31 - 1")
    if np.all(row_weight == 1):
        return table.replace(cumulative_weight=None)
    return table.replace(cumulative_weight=np.cumsum(row_weight, dtype=np.int64).astype(np.int32))


def draw_share(table: StepTable, rows: slice) -> float:
    """The share of `draw_rows`' draws that land in `rows` (a contiguous range of the table's
    rows, say one source's of `load_step_table`)."""
    start, stop, _ = rows.indices(table.size)
    if stop <= start:
        return 0.0
    if table.cumulative_weight is None:
        return (stop - start) / table.size
    cum = np.asarray(table.cumulative_weight, np.int64)
    return float(cum[stop - 1] - (cum[start - 1] if start else 0)) / float(cum[-1])


def random_episode_split(path: str, holdout: float, seed: int = 0) -> tuple[list[int], list[int]]:
    """(training, held-out) episode indices: a random `holdout` share of the episodes, chosen
    by `seed` (split by episode, not by step; `offline.datastore.strided_episode_split` holds out
    every n-th episode instead)."""
    n = len(demos.DemoDataset(path))
    order = np.random.default_rng(seed).permutation(n)
    k = int(round(n * holdout))
    return sorted(order[k:].tolist()), sorted(order[:k].tolist())


def random_shift(images: jnp.ndarray, key: jax.Array, max_shift: int, n_views: int = 1) -> jnp.ndarray:
    """Each image [B, H, W, C] translated by its own random integer offset in
    [-max_shift, max_shift]^2, borders replicated (the random-shift augmentation of DrQ).
    An image of `n_views` views tiled along W has each view shifted on its own."""
    if max_shift == 0:
        return images
    b, h, w, c = images.shape
    if n_views > 1:
        views = images.reshape(b, h, n_views, w // n_views, c).transpose(0, 2, 1, 3, 4).reshape(b * n_views, h, w // n_views, c)
        views = random_shift(views, key, max_shift)
        return views.reshape(b, n_views, h, w // n_views, c).transpose(0, 2, 1, 3, 4).reshape(b, h, w, c)
    padded = jnp.pad(images, ((0, 0), (max_shift, max_shift), (max_shift, max_shift), (0, 0)), mode="edge")
    offsets = jax.random.randint(key, (b, 2), 0, 2 * max_shift + 1)
    return jax.vmap(lambda im, o: jax.lax.dynamic_slice(im, (o[0], o[1], 0), (h, w, im.shape[-1])))(padded, offsets)


def draw_rows(table: StepTable, key: jax.Array, batch: int) -> jnp.ndarray:
    """`batch` random row indices [B] of the table, drawn with replacement: uniformly, or, where
    the table holds row weights, each row in proportion to its weight (an integer drawn below
    the weights' total, located in their running sum by binary search: exact, and O(B log N))."""
    if table.cumulative_weight is None:
        return jax.random.randint(key, (batch,), 0, table.size)
    cum = table.cumulative_weight
    return jnp.searchsorted(cum, jax.random.randint(key, (batch,), 0, cum[-1]), side="right").astype(jnp.int32)


def sample_batch(table: StepTable, key: jax.Array, batch: int, tok: ActionTokenizer, image_shift: int = 0,
                 n_views: int = 1):
    """A random minibatch (`draw_rows`): (vla.Observation, action token ids [B, 7]), each view
    of the images optionally randomly shifted by up to `image_shift` pixels."""
    k_idx, k_shift = jax.random.split(key)
    i = draw_rows(table, k_idx, batch)
    obs = vla.Observation(image=random_shift(table.image[i], k_shift, image_shift, n_views), instruction=table.instruction[i],
                          proprio=table.proprio[i])
    return obs, tok.to_ids(table.action[i])
