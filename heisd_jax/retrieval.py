"""The retrieval datastore of HeiSD's retrieval drafts (REST-style; HeiSD's use: our design).

Keys describe where the robot is in a task: the last `history` actions (normalised to
[-1, 1] by the target's tokenizer; zeros before the episode start), the end-effector
position (scaled, `pos_scale` per metre), its quaternion and jaw opening, i.e. the proprio
vector; values are the 7 tokens of the action taken next, tokenized by the target's
tokenizer. Entries carry their task (global task index): a query only matches its own task.

`query` is exact k-nearest neighbours on device: squared distances by one matmul,
`lax.top_k`, a static number of candidates with a validity mask (same task, within
`max_dist`). Saved as one .npz + meta.json beside the checkpoints, tied to the target's
tokenizer and checkpoint fingerprint; a datastore built for another target is refused.
Keys are stored as float16 (half the size; a key's entries are O(1), so the rounding,
~1e-3 relative, is far below the distances that separate neighbours) and used as float32.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
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


def make_keys(spec: KeySpec, tok: ActionTokenizer, prev_actions, proprio) -> jnp.ndarray:
    """Keys [..., dim] from the last `history` actions [..., history, 7] (oldest first; zeros
    where none) and the proprio vector [..., 8]."""
    prev = jnp.clip(tok.normalize(jnp.asarray(prev_actions, jnp.float32)), -1, 1)
    prev = prev.reshape(prev.shape[:-2] + (spec.history * ACTION_DIM,))
    proprio = jnp.asarray(proprio, jnp.float32)
    return jnp.concatenate([prev, proprio[..., :3] * spec.pos_scale, proprio[..., 3:]], -1)


def episode_history(actions: np.ndarray, history: int) -> np.ndarray:
    """[T, history, 7]: for each step, the actions of the `history` steps before it."""
    t = len(actions)
    padded = np.concatenate([np.zeros((history, ACTION_DIM), actions.dtype), actions])
    return np.stack([padded[i: i + history] for i in range(t)])


def build(spec: KeySpec, tok: ActionTokenizer, episodes) -> Datastore:
    """episodes: iterable of (global task index, actions [T, 7], proprio [T, 8])."""
    hist, acts, props, task = [], [], [], []
    for task_id, actions, proprio in episodes:  # host-side gathering; one device call below
        hist.append(episode_history(np.asarray(actions, np.float32), spec.history))
        acts.append(np.asarray(actions, np.float32))
        props.append(np.asarray(proprio, np.float32))
        task.append(np.full(len(actions), task_id, np.int32))
    if not acts:
        raise ValueError("no episodes to build a datastore from")
    k = np.asarray(make_keys(spec, tok, np.concatenate(hist), np.concatenate(props)), np.float32)
    tokens = np.asarray(tok.encode(jnp.asarray(np.concatenate(acts))))
    return Datastore(keys=jnp.asarray(k), sq_norms=jnp.asarray((k * k).sum(-1)),
                     tokens=jnp.asarray(tokens, jnp.int32), task=jnp.asarray(np.concatenate(task)))


def subsample(store: Datastore, stride: int) -> Datastore:
    """Every `stride`-th entry (consecutive control steps are near-duplicate keys at 20 Hz;
    a smaller datastore ships and queries faster)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    return jax.tree.map(lambda x: x[::stride], store)


def split_episodes(n_episodes: int, holdout: float) -> tuple[list[int], list[int]]:
    """(datastore episodes, held-out episodes): every round(1/holdout)-th episode is held
    out (for calibrating the boundary on trajectories the datastore has not seen)."""
    if not 0 <= holdout < 1:
        raise ValueError(f"holdout must be in [0, 1), got {holdout}")
    if holdout == 0:
        return list(range(n_episodes)), []
    every = max(2, round(1 / holdout))
    held = [i for i in range(n_episodes) if i % every == every - 1]
    return [i for i in range(n_episodes) if i % every != every - 1], held


def demo_features(path: str | os.PathLike, episodes: list[int] | None = None) -> np.ndarray:
    """The kinematic features (`heisd_jax.kinematics.features`) of every step of the demos
    [N, 5], the previous velocity being the episode's previous step's (zero at the start)."""
    from envs import demos  # noqa: PLC0415
    from heisd_jax import kinematics  # noqa: PLC0415

    ds = demos.DemoDataset(path)
    cols = {k: [] for k in ("ee_vel", "ee_ang_vel", "ee_acc", "gripper_vel", "prev")}
    for i in range(len(ds)) if episodes is None else episodes:  # gathered on the host, one device call
        ep = ds.episode(i)
        v = np.asarray(ep["ee_vel"], np.float32)
        cols["prev"].append(np.concatenate([np.zeros((1, 3), np.float32), v[:-1]]))
        for k in ("ee_vel", "ee_ang_vel", "ee_acc", "gripper_vel"):
            cols[k].append(np.asarray(ep[k], np.float32))
    c = {k: np.concatenate(v) for k, v in cols.items()}
    return np.asarray(kinematics.features(c["ee_vel"], c["ee_ang_vel"], c["ee_acc"], c["gripper_vel"], c["prev"]))


def build_from_demos(path: str | os.PathLike, spec: KeySpec, tok: ActionTokenizer,
                     episodes: list[int] | None = None) -> Datastore:
    """A datastore of a demos dataset (envs.demos), keyed by global task index."""
    from envs import demos, tasks as tasks_lib  # noqa: PLC0415

    ds = demos.DemoDataset(path)
    names = [t.name for t in tasks_lib.ALL_TASKS]
    idx = range(len(ds)) if episodes is None else episodes

    def gen():
        for i in idx:
            task = ds.episodes[i]["task"]
            if task not in names:
                raise ValueError(f"{path}: episode {i} has unknown task {task!r}")
            ep = ds.episode(i)
            yield names.index(task), np.asarray(ep["action"], np.float32), np.asarray(ep["proprio"], np.float32)
    return build(spec, tok, gen())


VALUES = ("demo", "target")  # what a key's value holds: the demo's next action, or the target's own choice


def target_values(tparams, cfg, path: str | os.PathLike, episodes: list[int] | None = None,
                  batch: int = 256) -> np.ndarray:
    """The target's greedy AR tokens [N, 7] on every demo step's observation (in
    `build_from_demos` order). Retrieved drafts are verified against the target's choices,
    and the target imitates the expert only approximately: values it would choose itself
    are accepted far more often (as EAGLE trains its drafter on the target's tokens)."""
    from heisd_jax import data, vla  # noqa: PLC0415

    steps = data.load_steps(str(path), episodes)
    n = len(steps.action)
    decode = jax.jit(lambda p, o: vla.ar_decode(p, cfg, o)[0])
    out = []
    for s in range(0, n, batch):
        idx = np.arange(s, s + batch) % n  # static shape: wrap the last batch
        obs = vla.Observation(image=jnp.asarray(steps.image[idx]), instruction=jnp.asarray(steps.instruction[idx]),
                              proprio=jnp.asarray(steps.proprio[idx]))
        out.append(np.asarray(decode(tparams, obs))[: min(batch, n - s)])
    return np.concatenate(out).astype(np.int32)


def with_values(store: Datastore, tokens: np.ndarray) -> Datastore:
    if tokens.shape != store.tokens.shape:
        raise ValueError(f"values {tokens.shape} do not match the datastore's {store.tokens.shape}")
    return store.replace(tokens=jnp.asarray(tokens, jnp.int32))


def query(store: Datastore, keys: jnp.ndarray, task: jnp.ndarray, n: int, max_dist: float = jnp.inf):
    """Exact kNN within the query's task. keys [B, dim], task [B] -> (candidate tokens
    [B, n, 7], squared distances [B, n], valid [B, n])."""
    d2 = (keys * keys).sum(-1, keepdims=True) - 2.0 * keys @ store.keys.T + store.sq_norms[None]
    d2 = jnp.where(store.task[None] == task[:, None], jnp.maximum(d2, 0.0), jnp.inf)
    neg, idx = jax.lax.top_k(-d2, n)
    dist = -neg
    return store.tokens[idx], dist, jnp.isfinite(dist) & (dist <= max_dist)


def save(path: str | os.PathLike, store: Datastore, spec: KeySpec, tok: ActionTokenizer, target_fingerprint: str,
         extra: dict | None = None) -> None:
    """Writes <path>/datastore.npz and meta.json via a temporary directory and a rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=False)
    np.savez_compressed(tmp / "datastore.npz", keys=np.asarray(store.keys, np.float16),
                        bins=np.asarray(np.asarray(store.tokens) - tok.first_action_id, np.uint8),
                        task=np.asarray(store.task, np.uint8))
    meta = dict(format=FORMAT, key_spec=dataclasses.asdict(spec), tokenizer=tok.to_dict(),
                target_fingerprint=target_fingerprint, size=store.size, **(extra or {}))
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old)
    else:
        os.replace(tmp, path)


def load(path: str | os.PathLike, tok: ActionTokenizer, target_fingerprint: str) -> tuple[Datastore, KeySpec, dict]:
    """(datastore, key spec, meta); refuses one built for another tokenizer or target."""
    path = Path(path)
    try:
        meta = json.loads((path / "meta.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"no readable datastore at {path}: {e}") from e
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
    store = Datastore(keys=jnp.asarray(keys), sq_norms=jnp.asarray((keys * keys).sum(-1)), tokens=jnp.asarray(tokens),
                      task=jnp.asarray(task))
    return store, spec, meta
