"""Acceptance rules: which drafted action tokens the target's greedy tokens accept.

Token-wise (each drafted token on its own, Spec-VLA): `strict` (the same bin: lossless,
speculative decoding equals AR token for token) and `token_relaxed` (within `relax_bins`
bins). Sequence-wise for whole retrieved actions (our design, docs/method.md):
`seq_relaxed` bounds each token's bin distance and the weighted cumulative distance of the
accepted prefix, and requires the gripper token to agree on open/closed. Verify-skip (the
paper's) decides when a retrieved action is executed without a target pass.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp

from heisd_jax.tokenizer import ACTION_DIM, N_BINS

GRIPPER_DIM = ACTION_DIM - 1
TOKEN_RULES = ("strict", "token_relaxed")  # drafter trees: each node accepted on its own
ACTION_RULES = ("strict", "token_relaxed", "seq_relaxed")  # retrieved whole actions: an accepted prefix
RELAX_BINS = 9  # token_relaxed's window where none is given (drafter trees and retrieved actions)


def check_rule(rule: str, valid: tuple[str, ...], what: str = "acceptance") -> None:
    if rule not in valid:
        raise ValueError(f"unknown {what} {rule!r}; valid: {', '.join(valid)}")


def token_accepted(rule: str, relax_bins: int, draft_bins: jnp.ndarray, target_bins: jnp.ndarray) -> jnp.ndarray:
    """Token-wise rule on action bins (0..255): draft == target (strict) or within relax_bins."""
    if rule == "strict":
        return draft_bins == target_bins
    return jnp.abs(draft_bins - target_bins) <= relax_bins


@dataclasses.dataclass(frozen=True)
class SeqRelaxedConfig:
    """HeiSD's defaults (the paper's 15 / 42, `hybrid.PAPER`, cost closed-loop success on our
    suites, docs/method.md)."""
    r_max: int = 9  # no token further than this from the target's bin
    r_seq: int = 24  # bound on the weighted cumulative bin distance of the accepted prefix
    weights: tuple[float, ...] = (1.0,) * ACTION_DIM

    def __post_init__(self):
        if not 0 <= self.r_max < N_BINS or self.r_seq < 0:
            raise ValueError(f"need 0 <= r_max < {N_BINS} and r_seq >= 0, got {self.r_max}, {self.r_seq}")
        if len(self.weights) != ACTION_DIM or any(w < 0 for w in self.weights):
            raise ValueError(f"weights need {ACTION_DIM} non-negative entries, got {self.weights}")


def gripper_closed(bins: jnp.ndarray) -> jnp.ndarray:
    return bins >= N_BINS // 2


def seq_relaxed_length(draft_bins: jnp.ndarray, target_bins: jnp.ndarray, cfg: SeqRelaxedConfig) -> jnp.ndarray:
    """Accepted prefix length [...] of a drafted action [..., 7] against the target's greedy
    bins [..., 7] (each conditioned on the draft prefix before it): the longest j with
    sum_{i<j} w_i |d_i - t_i| <= r_seq, every |d_i - t_i| <= r_max, and the gripper token
    agreeing on open/closed."""
    diff = jnp.abs(draft_bins - target_bins)
    ok = (diff <= cfg.r_max) & (jnp.cumsum(diff * jnp.asarray(cfg.weights), -1) <= cfg.r_seq)
    grip = gripper_closed(draft_bins[..., GRIPPER_DIM]) == gripper_closed(target_bins[..., GRIPPER_DIM])
    ok = ok.at[..., GRIPPER_DIM].set(ok[..., GRIPPER_DIM] & grip)
    return jnp.sum(jnp.cumprod(ok.astype(jnp.int32), -1), -1)


SKIP_SOURCES = ("retrieval", "recent")  # what a skipped step executes: the datastore's top action, or the last one


@dataclasses.dataclass(frozen=True)
class SkipConfig:
    """HeiSD's verify-skip: the last action repeated (the paper's source, the datastore's top
    candidate, is rarely confident enough to fire on the shipped stack; `hybrid.PAPER`)."""
    enabled: bool = True
    source: str = "recent"  # "retrieval": the datastore's top candidate (paper); "recent": repeat the last action
    eps: float = 0.05  # retrieval: nearest-key squared distance under which retrieval is trusted
    r_agree: int = 6  # retrieval: the top `n_agree` candidates agree within this many bins on every token
    n_agree: int = 3
    n_confirm: int = 1  # recent: the last this many verified steps each repeated their previous action
    k_skip: int = 2  # at most this many consecutive skipped target passes (longer runs cost closed-loop success)
    # Skip only where the kinematic metric M is at most this (coarse motion; the default: in the
    # whole retrieval regime). A skipped step repeats or retrieves an action without the target's
    # look at the image, which costs most where the motion is fine (high M); in a replay a
    # smaller k_skip bounded the error as well for the same share of skips (docs/method.md),
    # hence off by default.
    max_metric: float = math.inf
    # Source "recent": a verified step also counts as a repeat (towards n_confirm) when the
    # target's action is within these sequence-wise bounds of the last one (seq_relaxed's rule,
    # read from the same verification pass), even where a tighter acceptance executed the
    # target's own action instead. Tight r_max / r_seq keep the executed actions on the
    # target's, which relaxed acceptance slows down (docs/method.md), while the skip still
    # fires wherever the motion repeats loosely. None (both): a repeat is an executed action
    # equal to the last one.
    repeat_r_max: int | None = None
    repeat_r_seq: int | None = None

    def __post_init__(self):
        if self.source not in SKIP_SOURCES:
            raise ValueError(f"unknown skip source {self.source!r}; valid: {', '.join(SKIP_SOURCES)}")
        if (self.repeat_r_max is None) != (self.repeat_r_seq is None):
            raise ValueError(f"give both repeat_r_max and repeat_r_seq or neither, got {self.repeat_r_max}, "
                             f"{self.repeat_r_seq}")
        if self.repeat_r_max is not None:
            if self.source != "recent":
                raise ValueError("repeat_r_max / repeat_r_seq bound what counts as a repeat of the last action: "
                                 "they need skip source 'recent'")
            if not 0 <= self.repeat_r_max < N_BINS or self.repeat_r_seq < 0:
                raise ValueError(f"need 0 <= repeat_r_max < {N_BINS} and repeat_r_seq >= 0, got "
                                 f"{self.repeat_r_max}, {self.repeat_r_seq}")
        if self.eps < 0 or self.r_agree < 0 or self.n_agree < 1 or self.n_confirm < 1 or self.k_skip < 0 \
                or not self.max_metric >= 0:
            raise ValueError(f"need eps >= 0, r_agree >= 0, n_agree >= 1, n_confirm >= 1, k_skip >= 0, "
                             f"max_metric >= 0: {self}")


def repeat_bounds(cfg: SkipConfig) -> SeqRelaxedConfig | None:
    """The bounds within which a verified step's target action repeats the last action (None:
    only an executed action equal to it counts)."""
    return None if cfg.repeat_r_max is None else SeqRelaxedConfig(cfg.repeat_r_max, cfg.repeat_r_seq)


def may_skip(cfg: SkipConfig, in_retrieval: jnp.ndarray, dist: jnp.ndarray, cand_bins: jnp.ndarray,
             valid: jnp.ndarray, last_whole: jnp.ndarray, skips: jnp.ndarray) -> jnp.ndarray:
    """Verify-skip with source "retrieval" (the paper's): whether a row executes its top
    retrieved action without a target pass. dist [B, N]
    squared distances, cand_bins [B, N, 7], valid [B, N], last_whole [B] (the last verified
    retrieval action was accepted whole), skips [B] consecutive skips so far."""
    if not cfg.enabled or cfg.k_skip == 0:
        return jnp.zeros(in_retrieval.shape, bool)
    top = cand_bins[:, : cfg.n_agree]
    agree = jnp.all(jnp.abs(top - top[:, :1]) <= cfg.r_agree, axis=(1, 2)) & jnp.all(valid[:, : cfg.n_agree], 1)
    return in_retrieval & (dist[:, 0] <= cfg.eps) & agree & last_whole & (skips < cfg.k_skip)


def may_repeat(cfg: SkipConfig, in_retrieval: jnp.ndarray, last_valid: jnp.ndarray, repeats: jnp.ndarray,
               skips: jnp.ndarray) -> jnp.ndarray:
    """Verify-skip with source "recent": whether a row executes its last action again without a
    target pass. last_valid [B] (the row has a last action), repeats [B] the number of verified
    steps in a row whose action repeated the one before it (it was accepted whole as a
    candidate), skips [B] consecutive skips so far. A skipped step keeps `repeats`, so each
    verification after `k_skip` skips must repeat again for the skipping to go on."""
    if not cfg.enabled or cfg.k_skip == 0:
        return jnp.zeros(in_retrieval.shape, bool)
    return in_retrieval & last_valid & (repeats >= cfg.n_confirm) & (skips < cfg.k_skip)


def prefix_length(rule: str, relax_bins: int, seq: SeqRelaxedConfig, draft_bins: jnp.ndarray,
                  target_bins: jnp.ndarray) -> jnp.ndarray:
    """Accepted prefix length [...] of drafted actions [..., 7] against the target's greedy
    bins [..., 7] (token i's conditioned on the draft's tokens before it), under `rule`
    (one of ACTION_RULES)."""
    if rule == "seq_relaxed":
        return seq_relaxed_length(draft_bins, target_bins, seq)
    ok = token_accepted(rule, relax_bins, draft_bins, target_bins)
    return jnp.sum(jnp.cumprod(ok.astype(jnp.int32), -1), -1)
