"""What a policy sees at one control step: the camera image, the instruction as token ids,
and proprioception, batched, with the instruction format the decode core assumes: ids in
[0, TEXT_VOCAB), PAD_ID padding, TEXT_LEN tokens. The simulator (`envs`, which imports
nothing of the decode core) has its own observation of the same fields and builds its
vocabulary to fit these numbers; tests pin the two together.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

PAD_ID = 0  # instruction padding: attention never reads these slots
TEXT_LEN = 20  # instruction tokens per observation: BOS, words, EOS, padding
TEXT_VOCAB = 36  # instruction vocabulary size of the shipped checkpoints (envs.language.VOCAB)


@struct.dataclass
class Observation:
    """Leading axes [...] are the batch: [B]."""

    image: jnp.ndarray  # [..., H, W * n_views, 3] uint8: views tiled left to right (envs.camera)
    instruction: jnp.ndarray  # [..., TEXT_LEN] int32 token ids, PAD_ID-padded
    proprio: jnp.ndarray  # [..., 8] float32: ee position, ee quaternion, jaw opening
