"""Builds the retrieval datastore from demonstrations (`python -m experiments.build_datastore`);
`heisd_jax.retrieval` loads and queries what `save` writes.

Keys and values are those of `heisd_jax.retrieval` (`make_keys`, `KeySpec`): for every demo
step, the `history` actions before it and its proprio vector; the value is the action taken
next (the demo's, or with `target_values` the target's own greedy choice on that step's
observation). The build runs on the host, with one device call for all keys.
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

from envs import demos, tasks as tasks_lib
from heisd_jax import kinematics, target_model, vla
from heisd_jax.harness import data
from heisd_jax.retrieval import FORMAT, Datastore, KeySpec, make_keys
from heisd_jax.tokenizer import ACTION_DIM, ActionTokenizer


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
    tokens = np.asarray(tok.to_ids(jnp.asarray(np.concatenate(acts))))
    return Datastore.of(k, tokens, np.concatenate(task))


def subsample(store: Datastore, stride: int) -> Datastore:
    """Every `stride`-th entry (consecutive control steps are near-duplicate keys at 20 Hz;
    a smaller datastore ships and queries faster)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    return jax.tree.map(lambda x: x[::stride], store)


def strided_episode_split(n_episodes: int, holdout: float) -> tuple[list[int], list[int]]:
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
                     episodes: list[int] | None = None, actions: np.ndarray | None = None) -> Datastore:
    """A datastore of a demos dataset (envs.demos), keyed by global task index. `actions`
    [N, 7] (the chosen episodes' steps in order) replaces the recorded actions in the keys'
    histories and the values, e.g. with what a policy executed where it drove (`executed_actions`)."""
    ds = demos.DemoDataset(path)
    names = [t.name for t in tasks_lib.ALL_TASKS]
    idx = list(range(len(ds)) if episodes is None else episodes)
    if actions is not None and len(actions) != sum(ds.episodes[i]["length"] for i in idx):
        raise ValueError(f"{len(actions)} actions given for {sum(ds.episodes[i]['length'] for i in idx)} steps")

    def gen():
        at = 0
        for i in idx:
            task = ds.episodes[i]["task"]
            if task not in names:
                raise ValueError(f"{path}: episode {i} has unknown task {task!r}")
            ep = ds.episode(i)
            n = ds.episodes[i]["length"]
            acts = ep["action"] if actions is None else actions[at: at + n]
            at += n
            yield names.index(task), np.asarray(acts, np.float32), np.asarray(ep["proprio"], np.float32)
    return build(spec, tok, gen())


# What a key's value holds: the demo's next action; the target's own choice on the demo's
# state; or, for episodes the target drove alone (`collect_demos --policy=TARGET --beta=0
# --action_noise=0`, whose recorded actions are the expert's labels), the target's action
# in both the keys' histories and the values: what it executed, as a run-time key holds.
VALUES = ("demo", "target", "rollout")


def executed_actions(tparams, cfg, tok: ActionTokenizer, path: str | os.PathLike,
                     episodes: list[int] | None = None) -> np.ndarray:
    """The actions [N, 7] a target executed on the steps of episodes it drove alone: its
    greedy tokens there (`target_values`), detokenized."""
    return np.asarray(tok.to_actions(jnp.asarray(target_values(tparams, cfg, path, episodes))), np.float32)


def target_values(tparams, cfg, path: str | os.PathLike, episodes: list[int] | None = None,
                  batch: int = 256) -> np.ndarray:
    """The target's greedy AR tokens [N, 7] on every demo step's observation (in
    `build_from_demos` order). Retrieved drafts are verified against the target's choices,
    and the target imitates the expert only approximately: values it would choose itself
    are accepted far more often (as EAGLE trains its drafter on the target's tokens)."""
    steps = data.load_steps(str(path), episodes)
    decode = jax.jit(lambda p, o: target_model.ar_decode(p, cfg, o)[0])
    return in_batches(lambda idx: decode(tparams, vla.Observation(image=steps.image[idx],
                                                                  instruction=steps.instruction[idx],
                                                                  proprio=steps.proprio[idx])),
                      len(steps.action), batch).astype(np.int32)


def in_batches(fn, n: int, batch: int):
    """fn(rows) over rows 0..n-1 in batches of `batch` (the last one wrapped around, so one
    compiled shape serves every batch); its outputs (arrays or a pytree of them, batched on
    the first axis) gathered on the host and concatenated [n, ...]."""
    outs = []
    for s in range(0, n, batch):
        out = jax.device_get(fn(np.arange(s, s + batch) % n))
        outs.append(jax.tree.map(lambda x, k=min(batch, n - s): np.asarray(x)[:k], out))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *outs)


def with_values(store: Datastore, tokens: np.ndarray) -> Datastore:
    if tokens.shape != store.tokens.shape:
        raise ValueError(f"values {tokens.shape} do not match the datastore's {store.tokens.shape}")
    return store.replace(tokens=jnp.asarray(tokens, jnp.int32))


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
