"""The instruction vocabulary: one word per token, built from every suite's instructions.
Ids follow the decode core's instruction format (`heisd_jax.observation`): PAD is id 0 and
an instruction is TEXT_LEN tokens."""

from __future__ import annotations

import numpy as np

from envs.tasks import ALL_TASKS
from heisd_jax.observation import PAD_ID, TEXT_LEN

PAD, BOS, EOS, UNK = "<pad>", "<bos>", "<eos>", "<unk>"
MAX_INSTRUCTION_TOKENS = TEXT_LEN  # BOS + words + EOS, padded


def _build_vocab() -> tuple[str, ...]:
    words = sorted({w for t in ALL_TASKS for w in t.instruction.split()})
    return (PAD, BOS, EOS, UNK, *words)


VOCAB: tuple[str, ...] = _build_vocab()
WORD_TO_ID = {w: i for i, w in enumerate(VOCAB)}
assert WORD_TO_ID[PAD] == PAD_ID


def encode(text: str, length: int = MAX_INSTRUCTION_TOKENS) -> np.ndarray:
    """Instruction text -> [length] int32 ids (BOS, words, EOS, PAD...)."""
    ids = [WORD_TO_ID[BOS]] + [WORD_TO_ID.get(w, WORD_TO_ID[UNK]) for w in text.lower().split()] + [WORD_TO_ID[EOS]]
    if len(ids) > length:
        raise ValueError(f"instruction has {len(ids)} tokens, more than {length}: {text!r}")
    return np.array(ids + [WORD_TO_ID[PAD]] * (length - len(ids)), np.int32)


def decode(ids) -> str:
    words = [VOCAB[int(i)] for i in ids]
    return " ".join(w for w in words if w not in (PAD, BOS, EOS))
