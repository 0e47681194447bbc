"""The instruction vocabulary: one word per token, built from every suite's instructions.
Ids follow the decode core's instruction format (`heisd_jax.observation`, which tests pin
these constants to): PAD is id 0 and an instruction is 20 tokens."""

from __future__ import annotations

import numpy as np

from envs.tasks import ALL_TASKS

PAD, BOS, EOS, UNK = "<pad>", "<bos>", "<eos>", "<unk>"
PAD_ID = 0
MAX_INSTRUCTION_TOKENS = 20  # BOS + words + EOS, padded


def _build_vocab() -> tuple[str, ...]:
    words = sorted({w for t in ALL_TASKS for w in t.instruction.split()})
    return (PAD, BOS, EOS, UNK, *words)


VOCAB: tuple[str, ...] = _build_vocab()
WORD_TO_ID = {w: i for i, w in enumerate(VOCAB)}
assert WORD_TO_ID[PAD] == PAD_ID


def to_ids(text: str, length: int = MAX_INSTRUCTION_TOKENS, unknown: str = "unk") -> np.ndarray:
    """Instruction text -> [length] int32 ids (BOS, words, EOS, PAD...). A word outside the
    vocabulary (the words of the suites' instructions, which the shipped target was trained on)
    becomes UNK with `unknown="unk"` (the policy then sees an instruction it never saw; it
    still decodes), or raises ValueError naming it with `unknown="error"`."""
    if unknown not in ("unk", "error"):
        raise ValueError(f"unknown={unknown!r}; valid: unk, error")
    words = text.lower().split()
    missing = [w for w in words if w not in WORD_TO_ID]
    if missing and unknown == "error":
        raise ValueError(f"instruction {text!r} has words outside the vocabulary: {missing}; the vocabulary is "
                         f"envs.language.VOCAB ({len(VOCAB) - 4} words)")
    ids = [WORD_TO_ID[BOS]] + [WORD_TO_ID.get(w, WORD_TO_ID[UNK]) for w in words] + [WORD_TO_ID[EOS]]
    if len(ids) > length:
        raise ValueError(f"instruction has {len(ids)} tokens, more than {length}: {text!r}")
    return np.array(ids + [WORD_TO_ID[PAD]] * (length - len(ids)), np.int32)


def to_text(ids) -> str:
    words = [VOCAB[int(i)] for i in ids]
    return " ".join(w for w in words if w not in (PAD, BOS, EOS))
