"""Checkpoint content checksums and the instruction-vocabulary check: a round trip loads,
weights changed after saving (same file sizes) are refused as corrupted, a checkpoint of
another vocabulary is refused where instructions meet it; parameters stored in bfloat16 come
back in bfloat16, checksum verified."""

import dataclasses
import json
import logging
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tiny_models
from envs import language
from heisd_jax import checkpoint, drafter, vla
from heisd_jax.harness import vla_policy
from heisd_jax.observation import Observation
from heisd_jax.spec_decode import decode_action
from heisd_jax.tokenizer import ActionTokenizer

CFG = tiny_models.CFG
VOCAB = tuple(language.VOCAB)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tiny policy and a drafter for it, saved once: (policy dir, drafter dir, params)."""
    root = tmp_path_factory.mktemp("ckpt")
    params = vla.init_params(CFG, jax.random.PRNGKey(0))
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    checkpoint.save_policy(root / "vla", params, CFG, tok, text_vocab=VOCAB)
    checkpoint.save_drafter(root / "drafter", drafter.init_params(CFG, jax.random.PRNGKey(1)), CFG, params)
    return root / "vla", root / "drafter", params


def _meta_file(path: Path) -> Path:
    return next(f for f in path.rglob("metadata") if f.parent.name == "meta")


def _copy_with_flipped_weights(src: Path, dst: Path) -> Path:
    """A copy whose largest weight file has 8 bytes inverted in the middle (same size)."""
    shutil.copytree(src, dst)
    f = max((f for f in (dst / "0" / "state").rglob("*") if f.is_file() and "ocdbt.process_0/d" in f.as_posix()),
            key=lambda f: f.stat().st_size)
    data = bytearray(f.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 8] = bytes(b ^ 0xFF for b in data[mid:mid + 8])
    f.write_bytes(bytes(data))
    return dst


def test_round_trip_records_and_verifies_the_checksum(saved):
    path, _, params = saved
    p2, cfg2, _, meta = checkpoint.load_policy(path, text_vocab=VOCAB)
    assert cfg2 == CFG and meta["checksum"] == checkpoint.checksum(params)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(p2)):
        np.testing.assert_array_equal(a, b)
        assert isinstance(b, jax.Array)  # on the device: a jitted call does not copy it in each time


def test_checksum_changes_with_any_weight(saved):
    params = saved[2]
    bumped = jax.tree.map(lambda x: x, params)
    bumped["head"] = {"kernel": params["head"]["kernel"].at[0, 0].add(1e-6)}
    assert checkpoint.checksum(bumped) != checkpoint.checksum(params)


@pytest.mark.parametrize("kind", ["vla", "drafter"])
def test_overwritten_weights_are_refused_as_corrupted(saved, tmp_path, kind):
    vla_path, drafter_path, params = saved
    bad = _copy_with_flipped_weights(vla_path if kind == "vla" else drafter_path, tmp_path / f"bad_{kind}")
    with pytest.raises(checkpoint.CheckpointError, match=f"checkpoint {bad} is corrupted"):
        if kind == "vla":
            checkpoint.load_policy(bad)
        else:
            checkpoint.load_drafter(bad, CFG, params)


def test_checkpoint_without_checksum_loads_with_a_warning(saved, tmp_path, caplog):
    old = tmp_path / "old"
    shutil.copytree(saved[0], old)
    f = _meta_file(old)
    meta = json.loads(f.read_text())
    del meta["checksum"]
    f.write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="heisd_jax.checkpoint"):
        checkpoint.load_policy(old)
    assert "records no checksum" in caplog.text


def test_another_instruction_vocabulary_is_refused_where_given(saved):
    path = saved[0]
    other = (*VOCAB[:-1], "zebra")
    with pytest.raises(checkpoint.CheckpointError, match=f"checkpoint {path} was trained with another instruction "
                                                         f"vocabulary: .* differ at id {len(VOCAB) - 1}"):
        checkpoint.load_policy(path, text_vocab=other)
    checkpoint.load_policy(path)  # without a vocabulary to compare: loads


def test_shipped_checkpoints_record_checksums_and_the_env_vocabulary():
    params, cfg, _, meta = checkpoint.load_policy(vla_policy.DEFAULT_CHECKPOINT, text_vocab=language.VOCAB)
    assert meta["checksum"].startswith("sha256:")
    _, dmeta = checkpoint.load_drafter(vla_policy.DEFAULT_DRAFTER, cfg, params)
    assert dmeta["checksum"].startswith("sha256:")


def test_bfloat16_round_trip_halves_the_file_and_decodes(saved, tmp_path):
    _, _, params = saved
    tok = ActionTokenizer(q01=(-1.0,) * 7, q99=(1.0,) * 7, vocab_size=CFG.vocab_size)
    path = tmp_path / "vla_bf16"
    checkpoint.save_policy(path, params, CFG, tok, text_vocab=VOCAB, param_dtype="bfloat16")
    p2, cfg2, _, meta = checkpoint.load_policy(path, text_vocab=VOCAB)
    # It computes in the precision it is stored in (a float32 checkpoint's config is unchanged).
    assert cfg2 == dataclasses.replace(CFG, dtype="bfloat16") and meta["param_dtype"] == "bfloat16"
    assert checkpoint.read_config(path) == cfg2 and checkpoint.load_policy(saved[0])[1] == CFG
    # A drafter serves its target at any numerics, not at another architecture.
    checkpoint.load_drafter(saved[1], dataclasses.replace(CFG, dtype="bfloat16", unroll=True), params)
    with pytest.raises(checkpoint.CheckpointError, match="target of another config"):
        checkpoint.load_drafter(saved[1], dataclasses.replace(CFG, n_layers=CFG.n_layers + 1), params)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(p2)):
        assert b.dtype == jnp.bfloat16
        np.testing.assert_array_equal(np.asarray(a.astype(jnp.bfloat16)), np.asarray(b))
    assert meta["checksum"] == checkpoint.checksum(p2)  # verified over the bytes as stored

    def size(p):
        return sum(f.stat().st_size for f in (p / "0" / "state").rglob("*") if f.is_file())
    assert size(path) < 0.6 * size(saved[0])
    bf16 = dataclasses.replace(CFG, dtype="bfloat16")
    obs = Observation(image=jnp.zeros((2, *CFG.image_shape), jnp.uint8), instruction=jnp.ones((2, CFG.text_len), jnp.int32),
                      proprio=jnp.zeros((2, CFG.proprio_dim)))
    tokens, stats = decode_action(p2, bf16, obs)
    assert tokens.shape == (2, 7) and not np.asarray(stats["invalid"]).any()
    with pytest.raises(ValueError, match="unknown param_dtype 'float16'; valid: float32, bfloat16"):
        checkpoint.save_policy(tmp_path / "x", params, CFG, tok, text_vocab=VOCAB, param_dtype="float16")
