"""Checkpoints (orbax): training state for resumption, and the small policy checkpoints we
ship in `checkpoints/` (parameters, model config, tokenizer statistics, instruction
vocabulary, a content checksum).

Orbax writes each step into a temporary directory and renames it when complete, so a crash
never corrupts the last good checkpoint. `load_policy` gives one-call loading with errors
that name the path and the problem; the checksum recorded at save time catches weights
overwritten later (shapes alone would not). Loading does not import the simulator: code
that feeds a policy env instructions passes the env's vocabulary (`text_vocab=`) to have a
checkpoint of another vocabulary refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from pathlib import Path
from typing import Sequence

import jax
import numpy as np
import orbax.checkpoint as ocp

from heisd_jax import drafter, vla
from heisd_jax.tokenizer import ActionTokenizer

FORMAT = "heisd-jax-policy-v1"
DATA_FILE_BYTES = 8 << 20  # OCDBT data files are split at 8 MiB (shipped files stay under 16 MiB)


class CheckpointError(ValueError):
    """A missing, truncated or mismatched checkpoint."""


def metadata(model_cfg: vla.VLAConfig, tok: ActionTokenizer, kind: str = "vla", extra: dict | None = None, *,
             text_vocab: Sequence[str]) -> dict:
    """A policy checkpoint's metadata. text_vocab: the instruction words by id, as the
    training demonstrations were encoded (the env's `envs.language.VOCAB`)."""
    return dict(format=FORMAT, kind=kind, config=dataclasses.asdict(model_cfg), tokenizer=tok.to_dict(),
                text_vocab=list(text_vocab), **(extra or {}))


def manager(directory: str | Path, max_to_keep: int = 2) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(Path(directory).absolute(),
                                 options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True))


def save(mngr: ocp.CheckpointManager, step: int, tree, meta: dict) -> None:
    mngr.save(step, args=ocp.args.Composite(
        state=ocp.args.PyTreeSave(tree, ocdbt_target_data_file_size=DATA_FILE_BYTES), meta=ocp.args.JsonSave(meta)))
    mngr.wait_until_finished()


def restore(mngr: ocp.CheckpointManager, abstract_tree, step: int | None = None):
    """(tree, meta) of `step` (default: the latest)."""
    step = mngr.latest_step() if step is None else step
    restore_args = ocp.checkpoint_utils.construct_restore_args(abstract_tree)
    out = mngr.restore(step, args=ocp.args.Composite(
        state=ocp.args.PyTreeRestore(abstract_tree, restore_args=restore_args), meta=ocp.args.JsonRestore()))
    return out["state"], out["meta"]


PARAM_DTYPES = ("float32", "bfloat16")


def save_policy(path: str | Path, params, model_cfg: vla.VLAConfig, tok: ActionTokenizer, extra: dict | None = None,
                *, text_vocab: Sequence[str], param_dtype: str = "float32"):
    """Writes a shippable policy checkpoint (parameters and their checksum) at `path`, its
    floating-point parameters stored in `param_dtype` (`PARAM_DTYPES`; bfloat16 halves the
    file, and `load_policy` gives them back in that dtype, checksum verified)."""
    if param_dtype not in PARAM_DTYPES:
        raise ValueError(f"unknown param_dtype {param_dtype!r}; valid: {', '.join(PARAM_DTYPES)}")
    params = as_param_dtype(params, param_dtype)
    meta = metadata(model_cfg, tok, extra=extra, text_vocab=text_vocab)
    save(manager(path, max_to_keep=1), 0, params, dict(meta, param_dtype=param_dtype, checksum=checksum(params)))


def as_param_dtype(tree, param_dtype: str):
    """`tree` with its floating-point leaves cast to `param_dtype` (other leaves unchanged)."""
    dt = jax.numpy.dtype(param_dtype)
    return jax.tree.map(lambda x: x.astype(dt) if jax.numpy.issubdtype(x.dtype, jax.numpy.floating) else x, tree)


def _read_meta(path: Path):
    if not path.is_dir():
        raise CheckpointError(f"no checkpoint at {path}: directory does not exist")
    mngr = manager(path)
    step = mngr.latest_step()
    if step is None:
        raise CheckpointError(f"no complete checkpoint step under {path}")
    try:
        meta = mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
    except Exception as e:  # orbax raises many types for damaged files
        raise CheckpointError(f"checkpoint {path} (step {step}): cannot read its metadata: {e}") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path}: format {meta.get('format') if isinstance(meta, dict) else '?'}, "
                              f"expected {FORMAT}")
    return mngr, step, meta


def _restore_params(path: Path, mngr, step, abstract, meta: dict):
    try:
        params, _ = restore(mngr, abstract, step)
    except Exception as e:
        raise CheckpointError(f"checkpoint {path} (step {step}): parameters missing, truncated, corrupted or not "
                              f"matching the config ({type(e).__name__}: {str(e)[:300]})") from e
    for a, b in zip(jax.tree.leaves(abstract), jax.tree.leaves(params)):
        if tuple(a.shape) != tuple(np.shape(b)):
            raise CheckpointError(f"checkpoint {path}: parameter shape {np.shape(b)} does not match config {a.shape}")
    verify_checksum(path, params, meta)
    # On the device once: a jitted call given host (numpy) leaves copies every one of them in
    # on every call (32 MB for the shipped target: ~2.5 ms on an H100 at batch 1, ~1.7 ms on CPU).
    return jax.device_put(params)


def checksum(params) -> str:
    """"sha256:<hex>" over every parameter leaf's path, dtype, shape and bytes, leaves in
    sorted path order: any changed weight changes it."""
    h = hashlib.sha256()
    for path, leaf in sorted(jax.tree_util.tree_leaves_with_path(params), key=lambda kv: jax.tree_util.keystr(kv[0])):
        x = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{jax.tree_util.keystr(path)}|{x.dtype.str}|{x.shape}|".encode())
        h.update(x.tobytes())
    return "sha256:" + h.hexdigest()


def verify_checksum(path: str | Path, params, meta: dict) -> None:
    """Refuses parameters whose checksum differs from the one in `meta` (the bytes changed
    after saving); a checkpoint saved without one loads with a warning."""
    want = meta.get("checksum")
    if want is None:
        logging.getLogger(__name__).warning("checkpoint %s records no checksum: its weights cannot be verified", path)
        return
    got = checksum(params)
    if got != want:
        raise CheckpointError(f"checkpoint {path} is corrupted: its parameters' checksum {got} differs from the "
                              f"{want} recorded when it was saved")


def check_vocabulary(path: str | Path, meta: dict, text_vocab: Sequence[str]) -> None:
    """Refuses a policy trained on another instruction vocabulary than `text_vocab` (the
    words by id, e.g. `envs.language.VOCAB`): its instruction ids would mean other words."""
    recorded, here = meta.get("text_vocab"), list(text_vocab)
    if recorded == here:
        return
    if recorded is None:
        raise CheckpointError(f"checkpoint {path} records no instruction vocabulary")
    first = next((i for i, (a, b) in enumerate(zip(recorded, here)) if a != b), min(len(recorded), len(here)))
    raise CheckpointError(f"checkpoint {path} was trained with another instruction vocabulary: {len(recorded)} "
                          f"words, the instructions here use {len(here)}; they first differ at id {first}")


def _config(path: Path, meta: dict) -> vla.VLAConfig:
    """The checkpoint's model config, computing in the dtype its parameters are stored in: a
    policy stored in bfloat16 runs in bfloat16 (its own precision, the one its evaluation
    measured) wherever it is loaded, not in float32 over bf16-rounded weights."""
    try:
        cfg = vla.VLAConfig(**meta["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {path}: bad config metadata: {e}") from e
    dtype = meta.get("param_dtype", "float32")
    if dtype not in PARAM_DTYPES:
        raise CheckpointError(f"checkpoint {path}: parameters stored as {dtype!r}; this version reads "
                              f"{', '.join(PARAM_DTYPES)}")
    return dataclasses.replace(cfg, dtype=dtype)


def read_config(path: str | Path) -> vla.VLAConfig:
    """The model config of a policy checkpoint (its metadata only: cheap)."""
    path = Path(path)
    return _config(path, _read_meta(path)[2])


def load_policy(path: str | Path, text_vocab: Sequence[str] | None = None):
    """(params, VLAConfig, ActionTokenizer, meta) from a policy checkpoint directory, the config
    computing in the parameters' stored dtype (`_config`). With
    `text_vocab` (the instruction words by id the caller's instructions use), a checkpoint
    trained on another vocabulary is refused (`check_vocabulary`)."""
    path = Path(path)
    mngr, step, meta = _read_meta(path)
    if meta.get("kind", "vla") != "vla":
        raise CheckpointError(f"checkpoint {path} holds a {meta.get('kind')!r}, not a VLA policy")
    if text_vocab is not None:
        check_vocabulary(path, meta, text_vocab)
    cfg = _config(path, meta)
    try:
        tok = ActionTokenizer.from_dict(meta["tokenizer"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {path}: bad tokenizer metadata: {e}") from e
    abstract = jax.eval_shape(lambda: as_param_dtype(vla.init_params(cfg, jax.random.PRNGKey(0)), cfg.dtype))
    return _restore_params(path, mngr, step, abstract, meta), cfg, tok, meta


def fingerprint(params) -> str:
    """A short content hash of a parameter pytree (ties a drafter to its target)."""
    h = hashlib.sha256()
    for path, leaf in sorted(jax.tree_util.tree_leaves_with_path(params), key=lambda kv: jax.tree_util.keystr(kv[0])):
        h.update(jax.tree_util.keystr(path).encode())
        h.update(np.ascontiguousarray(np.asarray(leaf, np.float32)).tobytes())
    return h.hexdigest()[:16]


def save_drafter(path: str | Path, dparams, target_cfg: vla.VLAConfig, target_params, extra: dict | None = None):
    """Writes a drafter checkpoint, tied to its target by the target's fingerprint (of the
    target's parameters as given: a target re-saved in bfloat16 loads with another
    fingerprint, so its drafter is saved against the loaded bfloat16 parameters)."""
    meta = dict(format=FORMAT, kind="drafter", config=dataclasses.asdict(target_cfg),
                target_fingerprint=fingerprint(target_params), **(extra or {}), checksum=checksum(dparams))
    save(manager(path, max_to_keep=1), 0, dparams, meta)


def load_drafter(path: str | Path, target_cfg: vla.VLAConfig, target_params):
    """(drafter params, meta); refuses a drafter trained for another target."""
    path = Path(path)
    mngr, step, meta = _read_meta(path)
    if meta.get("kind") != "drafter":
        raise CheckpointError(f"checkpoint {path} holds a {meta.get('kind')!r}, not a drafter")
    try:
        same_cfg = vla.VLAConfig(**meta.get("config", {})).architecture() == target_cfg.architecture()
    except (TypeError, ValueError):
        same_cfg = False
    if not same_cfg:
        raise CheckpointError(f"drafter {path} was trained for a target of another config")
    if meta.get("target_fingerprint") != fingerprint(target_params):
        raise CheckpointError(f"drafter {path} was trained for another target checkpoint (fingerprint "
                              f"{meta.get('target_fingerprint')} != {fingerprint(target_params)})")
    abstract = jax.eval_shape(lambda: drafter.init_params(target_cfg, jax.random.PRNGKey(0)))
    return _restore_params(path, mngr, step, abstract, meta), meta
