"""The HeiSD decode step: retrieval drafts or drafter trees, chosen per env by the kinematic
boundary, batched and jitted (docs/method.md).

Per env and control step (`step`):
  1. kinematics: the fused metric M from the end-effector's MJX kinematics and the
     hysteresis boundary choose the mode (retrieval for smooth transport, drafter for fine
     manipulation). Published: a kinematic metric decides; the formula is our design
     (`heisd_jax.kinematics`).
  2. retrieval: the env's key (recent actions, proprio) queries the datastore for
     `n_candidates` whole actions (exact kNN on device, `heisd_jax.retrieval`; 0: no query,
     the recent actions alone); the env's own
     last `recent_candidates` executed actions join them as further candidates (our design:
     the target's actions repeat from step to step far more often than the datastore's
     expert actions match them). The skipped action comes first: the datastore's top one, or
     with `skip.source="recent"` the env's last action.
  3. verify-skip: a confident retrieval-mode row executes its first candidate with no target
     pass, at most `k_skip` times in a row. Source "retrieval" (the paper's,
     `rules.may_skip`): the datastore's top action, when it is near and its neighbours
     agree; source "recent" (our design, `rules.may_repeat`): the last action again, once
     `n_confirm` verified steps in a row each accepted their previous action whole.
  4. one target pass for the other rows (`decode`): the prompt prefill, with the candidates'
     tokens appended as parallel chains under a tree mask (`verify="prefill"`: verification
     fused into the prefill, one pass) or checked in a second pass (`verify="separate"`).
     A row's best candidate keeps its accepted prefix under the retrieval acceptance rule
     (`strict`, `token_relaxed`, or HeiSD's sequence-wise `seq_relaxed`); the target's
     greedy token follows as the bonus; the rest of the action is decoded by drafter rounds
     (Spec-VLA), as for drafter-mode rows, which start from the prefill alone, or, with
     `continuation="ar"` (our design), by single-token target passes with no drafter at
     all: on an H200 at batch 1 a 4x2x8 round costs 0.46 ms and gains ~1.7 tokens, about
     what 1.7 AR passes (0.25 ms each) cost, while the drafter's prompt pass and hand-over
     add to every action.
Rows that need no target pass (skipped) are masked, and the target call itself is skipped
(`lax.cond`) when no row in the batch needs it. With `row_buckets` > 1 the rows that need it
are gathered into the smallest of the sizes B/k, 2B/k, .., B that holds them (`compact_rows`),
so skipped rows also save work at batch sizes above 1, at the price of k compiled copies.

With `strict` acceptance everywhere and verify-skip off (`HybridConfig.lossless`), the
tokens equal greedy AR decoding for any inputs.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from heisd_jax import acceptance as rules, budget as budget_lib, kinematics, retrieval, spec_decode, target_model, vla
from heisd_jax.tokenizer import ACTION_DIM, ActionTokenizer

MODES = ("hybrid", "retrieval", "drafter")  # hybrid: kinematic boundary; else every step in that mode
RETRIEVAL_ACCEPTANCE = rules.ACTION_RULES
VERIFY = ("prefill", "separate")
CONTINUATION = ("drafter", "ar")  # what decodes the rest of an action after the prefill (and its accepted prefix)


def _check(name, value, valid):
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(valid)}")


@dataclasses.dataclass(frozen=True)
class HybridConfig:
    """The hybrid decode's configuration. Its defaults are the shipped `heisd` method's (the
    `heisd_jax.harness.methods` record runs this config when given no settings; a datastore's
    calibration fills the metric scales, boundary and skip_eps); `PAPER` is the paper's.

    Relaxed where whole actions are drafted, strict where tokens are: retrieved candidates are
    accepted sequence-wise relaxed and may be executed unverified (verify-skip), and the
    drafter's trees that decode the rest of an action are verified strictly, so after the
    candidates the action is the target's greedy one, as with `continuation="ar"`. Relaxed
    trees (the paper's, `PAPER`) accept more per round but move the executed actions off the
    target's, and cost closed-loop success on our suites (docs/method.md)."""
    spec: spec_decode.SpecConfig = spec_decode.SpecConfig()  # drafter SD: strict trees
    mode: str = "hybrid"
    acceptance: str = "seq_relaxed"  # rule for retrieval drafts
    relax_bins: int = rules.RELAX_BINS  # token_relaxed on retrieval drafts
    seq: rules.SeqRelaxedConfig = rules.SeqRelaxedConfig()
    n_candidates: int = 4  # retrieved from the datastore
    recent_candidates: int = 4  # the env's own last executed actions, newest first (our design)
    max_dist: float = float("inf")  # candidates with a squared key distance above this are invalid
    verify: str = "prefill"
    continuation: str = "drafter"  # "ar": single-token target passes, no drafter at all (budget option "ar+retrieval")
    skip: rules.SkipConfig = rules.SkipConfig()
    metric: kinematics.MetricConfig = kinematics.MetricConfig()
    boundary: kinematics.BoundaryConfig = kinematics.BoundaryConfig()
    budget: budget_lib.BudgetConfig = budget_lib.BudgetConfig()  # auto: `spec`'s tree is replaced per step
    row_buckets: int = 1  # rows needing a target pass run in the smallest of this many batch fractions (1: all)

    def __post_init__(self):
        _check("mode", self.mode, MODES)
        _check("retrieval acceptance", self.acceptance, RETRIEVAL_ACCEPTANCE)
        _check("verify", self.verify, VERIFY)
        _check("continuation", self.continuation, CONTINUATION)
        if self.n_candidates < 0 or self.recent_candidates < 0:
            raise ValueError(f"n_candidates and recent_candidates must be >= 0, got {self.n_candidates}, "
                             f"{self.recent_candidates}")
        if self.n_candidates + self.recent_candidates < 1:
            raise ValueError("nothing to verify: n_candidates (retrieved) + recent_candidates must be >= 1")
        if self.skip.enabled and self.mode != "drafter":
            if self.skip.source == "retrieval" and self.n_candidates == 0:
                raise ValueError("verify-skip from retrieval executes the datastore's top candidate: with "
                                 "n_candidates=0 (recent actions only), switch skip off or use skip source 'recent'")
            if self.skip.source == "recent" and self.recent_candidates == 0:
                raise ValueError("verify-skip from recent actions repeats the last one: it needs recent_candidates "
                                 ">= 1")
        if not 0 <= self.relax_bins < 256:
            raise ValueError(f"relax_bins must be in 0..255, got {self.relax_bins}")
        if self.max_dist <= 0:
            raise ValueError(f"max_dist must be > 0, got {self.max_dist}")
        if self.row_buckets < 1:
            raise ValueError(f"row_buckets must be >= 1, got {self.row_buckets}")
        if self.acceptance == "strict" and self.skip.enabled and self.mode != "drafter":
            raise ValueError("verify-skip executes unverified actions: with strict (lossless) retrieval acceptance, "
                             "switch skip off")

    @property
    def n_verified(self) -> int:
        """Candidates verified per retrieval-mode step: the datastore's and the recent ones."""
        return self.n_candidates + self.recent_candidates

    @property
    def lossless(self) -> bool:
        """Tokens identical to greedy AR decoding."""
        uses_retrieval = self.mode != "drafter"
        uses_drafter = self.continuation == "drafter" or self.budget.mode == "auto"
        return (not uses_drafter or self.spec.acceptance == "strict") and (
            not uses_retrieval or (self.acceptance == "strict" and not self.skip.enabled))

    def check_fits(self, cfg: vla.VLAConfig):
        self.spec.check_fits(cfg)
        if self.budget.mode == "auto":
            for tree in self.budget.trees:
                budget_lib.tree_spec(self.spec, tree).check_fits(cfg)
        need = cfg.prompt_len + self.n_verified * (ACTION_DIM - 1)
        if need > cfg.cache_slots:
            raise ValueError(f"{self.n_candidates} retrieved + {self.recent_candidates} recent candidates need {need} "
                             f"cache slots, the model has {cfg.cache_slots}; n_candidates + recent_candidates must "
                             f"be <= {(cfg.cache_slots - cfg.prompt_len) // (ACTION_DIM - 1)}")


# The paper's HeiSD: sequence-wise acceptance at r_max 15 / r_seq 42, verify-skip on the
# datastore's top candidate, no recent-action candidates, one fixed draft tree, relaxed.
PAPER = HybridConfig(spec=spec_decode.SpecConfig(acceptance="token_relaxed", relax_bins=rules.RELAX_BINS),
                     seq=rules.SeqRelaxedConfig(r_max=15, r_seq=42), recent_candidates=0,
                     skip=rules.SkipConfig(source="retrieval", n_confirm=2, k_skip=3),
                     budget=budget_lib.BudgetConfig(mode="fixed"))


def candidate_block(cand: jnp.ndarray):
    """Candidates [B, N, 7] (token ids) as a verification block of N parallel chains of
    their first 6 tokens (the 7th is only checked): tokens [B, 6N], depth [B, 6N] (token i
    of a chain at prompt end + i) and the mask [B, 6N, 6N] (causal within a chain)."""
    b, n, _ = cand.shape
    c = ACTION_DIM - 1
    tokens = cand[:, :, :c].reshape(b, n * c)
    depth = jnp.broadcast_to(jnp.tile(jnp.arange(c), n), (b, n * c))
    intra = jnp.kron(jnp.eye(n, dtype=jnp.int32), jnp.tril(jnp.ones((c, c), jnp.int32))).astype(bool)
    return tokens, depth, jnp.broadcast_to(intra, (b, n * c, n * c))


STAT_KEYS = ("target_passes", "drafter_passes", "rounds", "tokens", "retrieval_verified", "retrieval_accepted",
             "retrieval_whole", "skipped", "last_within")


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class Accepted:
    """What one target pass over the prompt and the retrieved candidates leaves: the
    prompt's pass outputs (for the drafter), the best candidate and its accepted prefix
    (committed to the target's cache), and the target's own token after that prefix."""
    logits: jnp.ndarray  # [B, V] at the last prompt position
    hidden: jnp.ndarray  # [B, P, D] prompt hidden states
    prompt_x: jnp.ndarray  # [B, P, D] prompt embeddings
    cache: object  # the target's cache holding the prompt
    committed: object  # ... and the best candidate's accepted tokens 1..min(acc, 6)
    block_hidden: jnp.ndarray  # [B, 7, D] target hidden of the best candidate's chain
    best: jnp.ndarray  # [B, 7] token ids of the best candidate
    acc: jnp.ndarray  # [B] its accepted length, 0..7
    bonus: jnp.ndarray  # [B, 1] the target's token after the accepted prefix
    greedy_first: jnp.ndarray  # [B] the target's first token (id)
    passes: jnp.ndarray  # [B] target passes so far (the prefill, and a separate verification)
    last_within: jnp.ndarray  # [B] candidate 0 (the last action, skip source recent) within the skip's repeat bounds


def verify_candidates(tp, t: target_model.TargetModel, hcfg: HybridConfig, obs: vla.Observation, cand: jnp.ndarray,
                      cand_valid: jnp.ndarray, verify_rows: jnp.ndarray) -> Accepted:
    """The prefill, with the candidates [B, N, 7] verified inside it (`verify="prefill"`)
    or in a second pass (`"separate"`) for the rows `verify_rows` [B] (none: the prefill
    alone), and each row's best candidate by `hcfg`'s sequence acceptance."""
    cfg = t.cfg
    b, n, _ = cand.shape
    c = ACTION_DIM - 1
    block = candidate_block(cand)
    zeros = lambda shapes: jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)  # noqa: E731
    if hcfg.verify == "prefill":
        def fused(_):
            lg, h, x, blg, bh, cache, kv = t.prefill_with_block(tp, obs, *block)
            return lg, h, x, blg, bh.astype(cfg.dtype), cache, kv

        def plain(_):
            lg, h, x, cache = t.prefill(tp, obs)
            _, _, _, blg, bh, _, kv = zeros(jax.eval_shape(fused, None))  # the block pass's shapes, zero
            return lg, h, x, blg, bh, cache, kv
        # At batch 1 a drafter-mode step prefills without the block. In a batch some row nearly
        # always verifies, so the block-free prefill would be a second compiled copy of the
        # largest pass (in every row bucket's copy of the decode) that rarely runs; without it a
        # row's prompt pass no longer depends on whether another row verifies.
        if b == 1:
            logits, hidden, x, blogits, bhidden, cache, block_kv = jax.lax.cond(jnp.any(verify_rows), fused, plain, None)
        else:
            logits, hidden, x, blogits, bhidden, cache, block_kv = fused(None)
        passes = jnp.ones((b,), jnp.float32)
    else:
        logits, hidden, x, cache = t.prefill(tp, obs)

        def separate(cache):
            blg, bh, kv = t.cached_pass(tp, cache, *block)
            return blg, bh.astype(cfg.dtype), kv
        blogits, bhidden, block_kv = jax.lax.cond(jnp.any(verify_rows), separate,
                                                  lambda cache: zeros(jax.eval_shape(separate, cache)), cache)
        passes = 1.0 + verify_rows.astype(jnp.float32)

    first_id = cfg.first_action_id
    greedy1 = jnp.argmax(vla.action_logits(cfg, logits), -1)  # [B] bins
    node_greedy = jnp.argmax(vla.action_logits(cfg, blogits), -1).reshape(b, n, c)
    target_bins = jnp.concatenate([jnp.broadcast_to(greedy1[:, None, None], (b, n, 1)), node_greedy], -1)
    length = rules.prefix_length(hcfg.acceptance, hcfg.relax_bins, hcfg.seq, cand - first_id, target_bins)
    length = jnp.where(cand_valid & verify_rows[:, None], length, 0)
    best = jnp.argmax(length, 1)
    acc = jnp.max(length, 1)  # [B] 0..7
    best_cand = jnp.take_along_axis(cand, best[:, None, None], 1)[:, 0]  # [B, 7]
    best_target = jnp.take_along_axis(target_bins, best[:, None, None], 1)[:, 0] + first_id  # [B, 7]
    # The accepted prefix (tokens 1..acc) is kept and committed; the target's token acc+1 follows.
    bonus = jnp.take_along_axis(best_target, jnp.minimum(acc, c)[:, None], 1)  # [B, 1]
    bounds = rules.repeat_bounds(hcfg.skip)
    if bounds is None or hcfg.recent_candidates == 0:  # (bounds need skip source "recent": SkipConfig)
        last_within = jnp.zeros((b,), bool)
    else:  # the target's action, read from the last action's own chain, within the repeat bounds of it
        last_within = cand_valid[:, 0] & verify_rows & (
            rules.seq_relaxed_length(cand[:, 0] - first_id, target_bins[:, 0], bounds) == ACTION_DIM)
    chain = best[:, None] * c + jnp.minimum(jnp.arange(ACTION_DIM)[None], c - 1)  # block offsets of its nodes
    return Accepted(logits=logits, hidden=hidden, prompt_x=x, cache=cache,
                    committed=t.commit(cache, block_kv, chain, jnp.minimum(acc, c)),
                    block_hidden=jnp.take_along_axis(bhidden, chain[..., None], 1), best=best_cand, acc=acc,
                    bonus=bonus, greedy_first=greedy1 + first_id, passes=passes, last_within=last_within)


def continue_ar(tp, t: target_model.TargetModel, a: Accepted, skip: jnp.ndarray):
    """`decode`'s tail with `continuation="ar"`: a row keeps its best candidate's accepted
    tokens 1..acc (already committed) and the target's token acc+1 (from the same pass),
    and decodes the rest by single-token target passes; no drafter. Returns tokens [B, 7]
    (skipped rows: zeros) and stats."""
    i = jnp.arange(ACTION_DIM)[None]
    out = jnp.where(i < a.acc[:, None], a.best, jnp.where(i == a.acc[:, None], a.bonus, 0))
    n_out = jnp.where(skip, ACTION_DIM, jnp.minimum(a.acc + 1, ACTION_DIM))  # skipped rows are done
    out, steps = target_model.ar_continue(tp, t, a.committed, out, n_out)
    ran = (~skip).astype(jnp.float32)
    steps = steps.astype(jnp.float32)
    return out, {"target_passes": (a.passes + steps) * ran, "drafter_passes": jnp.zeros_like(ran),
                 "rounds": steps * ran, "retrieval_accepted": a.acc.astype(jnp.float32)}


def continue_drafter(tp, dp, t: target_model.TargetModel, spec: spec_decode.SpecConfig, obs: vla.Observation,
                     a: Accepted, skip: jnp.ndarray):
    """`decode`'s tail with `continuation="drafter"`: the drafter reads the prompt, then
    the accepted prefix (token 1 the root, tokens 2..acc its path, the target's token acc+1
    the bonus), and draft-verify rounds (`spec`) finish each row. Returns tokens [B, 7]
    (skipped rows: meaningless, `decode` replaces them) and stats."""
    b = a.acc.shape[0]
    first = jnp.where(a.acc >= 1, a.best[:, 0], a.greedy_first)
    s0 = spec_decode.start(tp, dp, t, a.logits, a.hidden, a.prompt_x, a.cache, obs, first=first,
                           slack=max(spec.depth, ACTION_DIM) + 1)
    n_acc = jnp.maximum(a.acc - 1, 0)
    rest = jnp.concatenate([a.best[:, 1:], jnp.zeros((b, 1), jnp.int32)], 1)  # tokens 2..7, pad
    tokens = jnp.where(jnp.arange(ACTION_DIM)[None] == n_acc[:, None], a.bonus, rest)
    v = spec_decode.Verified(n_accepted=n_acc, path=jnp.zeros((b, ACTION_DIM - 1), jnp.int32), tokens=tokens,
                             hidden=a.block_hidden, cache=a.committed)
    s1 = spec_decode.advance(tp, dp, t, s0, v)
    s1 = dataclasses.replace(s1, stats=dict(s1.stats, drafter_passes=s1.stats["drafter_passes"] + 1.0))
    s = spec_decode.select_state(t, a.acc >= 1, s1, s0)
    s = dataclasses.replace(s, n_out=jnp.where(skip, ACTION_DIM, s.n_out))  # skipped rows are done
    s = spec_decode.rounds(tp, dp, t, spec, s)
    ran = (~skip).astype(jnp.float32)
    return s.out[:, :ACTION_DIM], {"target_passes": (s.stats["target_passes"] - 1.0 + a.passes) * ran,
                                   "drafter_passes": s.stats["drafter_passes"] * ran,
                                   "rounds": s.stats["rounds"] * ran, "retrieval_accepted": a.acc.astype(jnp.float32)}


def decode(params, model: target_model.Model, hcfg: HybridConfig, obs: vla.Observation, cand: jnp.ndarray,
           cand_valid: jnp.ndarray, use_retrieval: jnp.ndarray, skip: jnp.ndarray):
    """One action per row. params: {"target", "drafter"}; cand [B, N, 7] retrieved token
    ids, cand_valid [B, N]; use_retrieval [B]: verify the candidates (else drafter SD from
    the prefill); skip [B]: execute cand[:, 0] without a target pass. Returns token ids
    [B, 7] and per-row stats (STAT_KEYS): target/drafter passes, rounds, tokens, whether the
    retrieval draft was verified, its accepted length and whether it was accepted whole,
    whether the row skipped, whether its last action was within the skip's repeat bounds of the
    target's (`SkipConfig.repeat_r_max`). model: a `vla.VLAConfig` or any `target_model.TargetModel`."""
    t = target_model.as_target(model)
    tp, dp = params["target"], params["drafter"]
    b = cand.shape[0]
    verify_rows = use_retrieval & ~skip

    def with_target(_):
        a = verify_candidates(tp, t, hcfg, obs, cand, cand_valid, verify_rows)
        if hcfg.continuation == "ar":
            out, stats = continue_ar(tp, t, a, skip)
        else:
            out, stats = continue_drafter(tp, dp, t, hcfg.spec, obs, a, skip)
        return jnp.where(skip[:, None], cand[:, 0], out), dict(stats, last_within=a.last_within.astype(jnp.float32))

    def all_skipped(_):
        z = jnp.zeros((b,), jnp.float32)
        return cand[:, 0], {"target_passes": z, "drafter_passes": z, "rounds": z, "retrieval_accepted": z,
                            "last_within": z}

    tokens, stats = jax.lax.cond(jnp.any(~skip), with_target, all_skipped, None)
    verified = verify_rows.astype(jnp.float32)
    stats.update(tokens=jnp.full((b,), ACTION_DIM, jnp.float32), retrieval_verified=verified,
                 retrieval_whole=verified * (stats["retrieval_accepted"] == ACTION_DIM), skipped=skip.astype(jnp.float32))
    return tokens, stats


def decode_ar(params, model: target_model.Model, obs: vla.Observation, cand: jnp.ndarray, skip: jnp.ndarray):
    """`decode`'s contract with plain AR for the rows that do not skip (no drafting at all)."""
    b = cand.shape[0]

    def with_target(_):
        tokens, passes = target_model.ar_decode(params["target"], model, obs)
        return jnp.where(skip[:, None], cand[:, 0], tokens), jnp.where(skip, 0.0, float(passes))

    tokens, passes = jax.lax.cond(jnp.any(~skip), with_target,
                                  lambda _: (cand[:, 0], jnp.zeros((b,), jnp.float32)), None)
    z = jnp.zeros((b,), jnp.float32)
    return tokens, {"target_passes": passes, "drafter_passes": z, "rounds": z, "retrieval_accepted": z, "last_within": z,
                    "tokens": jnp.full((b,), ACTION_DIM, jnp.float32), "retrieval_verified": z,
                    "retrieval_whole": z, "skipped": skip.astype(jnp.float32)}


def decode_auto(params, model: target_model.Model, hcfg: HybridConfig, bstate: budget_lib.BudgetState, option: jnp.ndarray,
                obs: vla.Observation, cand: jnp.ndarray, cand_valid: jnp.ndarray, use_retrieval: jnp.ndarray,
                skip: jnp.ndarray):
    """`decode` under budget option `option` (an index into `budget.options`, from
    `budget.choose`). Returns tokens, stats (with a one-hot `budget_<option>` per row) and
    the budget state updated with the rounds this batch needed."""
    opts = budget_lib.options(hcfg.budget, hcfg.mode)
    trees = hcfg.budget.trees
    wants_retrieval = jnp.asarray([opt.retrieval for opt in opts])[option]

    def branch(**change):
        hc = dataclasses.replace(hcfg, **change)
        return lambda _: decode(params, model, hc, obs, cand, cand_valid, use_retrieval & wants_retrieval, skip)

    branches = [lambda _: decode_ar(params, model, obs, cand, skip)]
    if any(o.tree is None and o.retrieval for o in opts):
        branches.append(branch(continuation="ar"))
    branches += [branch(spec=budget_lib.tree_spec(hcfg.spec, t), continuation="drafter") for t in trees]
    tokens, stats = jax.lax.switch(jnp.asarray(budget_lib.branch_index(opts, trees))[option], branches, None)
    ran = ~skip
    # what `ar+retrieval` would have needed after the same accepted prefix: a pass per token
    # left after the prefill's (rows that verified no candidate: acc 0, six passes)
    ar_rounds = jnp.max(jnp.where(ran, jnp.maximum(ACTION_DIM - 1 - stats["retrieval_accepted"], 0.0), 0.0))
    updated = budget_lib.update(hcfg.budget, bstate, opts, params["costs"], option, jnp.max(stats["rounds"]),
                                jnp.where(wants_retrieval, ar_rounds, -1.0))
    # A step where every row skips ran no option: it says nothing of any option's rounds.
    bstate = jax.tree.map(lambda new, old: jnp.where(jnp.any(ran), new, old), updated, bstate)
    b = cand.shape[0]
    for i, opt in enumerate(opts):
        stats[f"budget_{opt.name}"] = jnp.full((b,), option == i, jnp.float32)
    return tokens, stats, bstate


def bucket_sizes(batch: int, n_buckets: int) -> tuple[int, ...]:
    """The row counts `compact_rows` may run at: ceil(j * batch / n_buckets), j = 1..n, distinct."""
    return tuple(sorted({-(-j * batch // n_buckets) for j in range(1, n_buckets + 1)}))


def compact_rows(fn, rows, skip: jnp.ndarray, skip_tokens: jnp.ndarray, n_buckets: int, fill: dict):
    """Runs `fn(rows, skip) -> (tokens [b, 7], stats {key: [b]}, *extra)` on only as many rows
    as need a target pass: the rows with skip False, gathered (stable order) into the smallest
    of `bucket_sizes` that holds them, padded with skipped rows; the others get `skip_tokens`
    and `fill`'s stats (0 where not given). rows: a pytree of [B, ...] arrays. Each row's
    result is the same as in one call on the whole batch, up to the batch size's numerics."""
    b = skip.shape[0]
    sizes = bucket_sizes(b, n_buckets)
    if len(sizes) == 1:
        return fn(rows, skip)
    order = jnp.argsort(skip, stable=True)  # rows that need the target first

    def run(size):
        def call(_):
            if size == b:
                return fn(rows, skip)
            idx = order[:size]
            tokens, stats, *extra = fn(jax.tree.map(lambda x: x[idx], rows), skip[idx])
            full = {k: jnp.broadcast_to(jnp.asarray(fill.get(k, 0.0), v.dtype), (b,)).at[idx].set(v)
                    for k, v in stats.items()}
            return (skip_tokens.at[idx].set(tokens), full, *extra)
        return call
    need = jnp.sum(~skip)
    which = jnp.searchsorted(jnp.asarray(sizes), need)  # the first size >= need
    return jax.lax.switch(which, [run(size) for size in sizes], None)


@struct.dataclass
class HybridState:
    """What the HeiSD step carries from one control step to the next, per env."""
    prev_actions: jnp.ndarray  # [B, history, 7] executed actions, oldest first (zeros before the start)
    prev_lin_vel: jnp.ndarray  # [B, 3] end-effector velocity at the previous step
    boundary: kinematics.BoundaryState
    skips: jnp.ndarray  # [B] consecutive skipped target passes
    last_whole: jnp.ndarray  # [B] the last verified retrieval action was accepted whole
    repeats: jnp.ndarray  # [B] verified steps in a row whose action repeated the previous one
    recent: jnp.ndarray  # [B, recent_candidates, 7] token ids of the last executed actions, newest first
    recent_valid: jnp.ndarray  # [B, recent_candidates] (False before the episode has that many)
    budget: budget_lib.BudgetState | None = None  # batch-wide running estimates (budget "auto" only)


def init_state(batch: int, key_spec: retrieval.KeySpec, hcfg: HybridConfig | None = None) -> HybridState:
    bstate = None
    if hcfg is not None and hcfg.budget.mode == "auto":
        bstate = budget_lib.init_state(budget_lib.options(hcfg.budget, hcfg.mode))
    r = hcfg.recent_candidates if hcfg is not None else 0
    return HybridState(prev_actions=jnp.zeros((batch, key_spec.history, ACTION_DIM), jnp.float32),
                       prev_lin_vel=jnp.zeros((batch, 3), jnp.float32), boundary=kinematics.boundary_init((batch,)),
                       skips=jnp.zeros((batch,), jnp.int32), last_whole=jnp.zeros((batch,), bool),
                       repeats=jnp.zeros((batch,), jnp.int32),
                       recent=jnp.zeros((batch, r, ACTION_DIM), jnp.int32), recent_valid=jnp.zeros((batch, r), bool),
                       budget=bstate)


@struct.dataclass
class Kinematics:
    """End-effector kinematics per env (from MJX: `envs.proprio.EEKinematics`)."""
    lin_vel: jnp.ndarray  # [B, 3]
    ang_vel: jnp.ndarray  # [B, 3]
    lin_acc: jnp.ndarray  # [B, 3]
    gripper_vel: jnp.ndarray  # [B]


def step(params, model: target_model.Model, hcfg: HybridConfig, key_spec: retrieval.KeySpec, tok: ActionTokenizer,
         state: HybridState, obs: vla.Observation, kin: Kinematics, task: jnp.ndarray):
    """One HeiSD control step for a batch of envs. params: {"target", "drafter", "store"}
    (+ "costs", a `budget.Costs`, with budget "auto": then `state` comes from
    `init_state(..., hcfg)`); task [B]: global task indices (the datastore's). Returns (actions [B, 7] continuous,
    token ids [B, 7], the next state, per-row stats: `decode`'s plus the metric and the
    mode shares)."""
    t = target_model.as_target(model)
    cfg = t.cfg
    metric = kinematics.fused_metric(
        kinematics.features(kin.lin_vel, kin.ang_vel, kin.lin_acc, kin.gripper_vel, state.prev_lin_vel), hcfg.metric)
    boundary = kinematics.boundary_step(state.boundary, metric, hcfg.boundary)
    b = metric.shape[0]
    if hcfg.mode == "hybrid":
        use_retrieval = boundary.mode == kinematics.RETRIEVAL
    else:
        use_retrieval = jnp.full((b,), hcfg.mode == "retrieval")
    keys = retrieval.make_keys(key_spec, tok, state.prev_actions, obs.proprio)
    bstate = state.budget
    auto = hcfg.budget.mode == "auto"
    n = hcfg.n_candidates

    def no_query(_):
        return (jnp.full((b, n, ACTION_DIM), cfg.first_action_id, jnp.int32), jnp.full((b, n), jnp.inf, jnp.float32),
                jnp.zeros((b, n), bool))

    def query(_):
        return no_query(None) if n == 0 else retrieval.query(params["store"], keys, task, n, hcfg.max_dist)
    if auto:
        if bstate is None or "costs" not in params:
            raise ValueError('budget "auto" needs params["costs"] (cost_model.load_or_calibrate(...).costs()) and a '
                             "state from init_state(batch, key_spec, hcfg)")
        opts = budget_lib.options(hcfg.budget, hcfg.mode)
        option = budget_lib.choose(params["costs"], bstate, opts, jnp.any(use_retrieval), hcfg.budget.retry_share,
                                   hcfg.budget.margin)
        # Plain AR (option 0) means no retrieval work at all: no query (and so no verify-skip).
        cand, dist, valid = jax.lax.cond(option == 0, no_query, query, None)
    else:
        cand, dist, valid = query(None)
    # Skip only while the metric itself is in the retrieval regime (not merely held there by
    # dwell), and at most the skip's own bound on it.
    in_regime = use_retrieval & ((metric <= hcfg.boundary.tau_on) | (hcfg.mode == "retrieval")) \
        & (metric <= hcfg.skip.max_metric)
    if state.recent.shape[1] != hcfg.recent_candidates:
        raise ValueError(f"the state holds {state.recent.shape[1]} recent actions, the config wants "
                         f"{hcfg.recent_candidates}: make it with init_state(batch, key_spec, hcfg)")
    if hcfg.skip.source == "recent":  # the last action first: a skipped row executes it again
        has_last = jnp.any(state.recent_valid[:, :1], 1)  # False without recent candidates (skip is off then)
        skip = rules.may_repeat(hcfg.skip, in_regime, has_last, state.repeats, state.skips)
        cand = jnp.concatenate([state.recent, cand], 1)
        valid = jnp.concatenate([state.recent_valid, valid], 1)
    else:
        skip = rules.may_skip(hcfg.skip, in_regime, dist, cand - cfg.first_action_id, valid, state.last_whole,
                              state.skips)
        cand = jnp.concatenate([cand, state.recent], 1)
        valid = jnp.concatenate([valid, state.recent_valid], 1)
    fill = {"tokens": float(ACTION_DIM), "skipped": 1.0}  # the stats of a row left out of the bucket
    if auto:
        fill.update({f"budget_{o.name}": (option == i).astype(jnp.float32)
                     for i, o in enumerate(budget_lib.options(hcfg.budget, hcfg.mode))})
        run = lambda r, sk: decode_auto(params, t, hcfg, bstate, option, *r, sk)  # noqa: E731
    else:
        run = lambda r, sk: decode(params, t, hcfg, *r, sk)  # noqa: E731
    tokens, stats, *new_budget = compact_rows(run, (obs, cand, valid, use_retrieval), skip, cand[:, 0],
                                              hcfg.row_buckets, fill)
    bstate = new_budget[0] if auto else bstate
    actions = tok.to_actions(tokens)
    whole = stats["retrieval_whole"] > 0
    if hcfg.recent_candidates:  # the executed action is the last one, or the target's is within the repeat bounds
        repeated = (state.recent_valid[:, 0] & jnp.all(tokens == state.recent[:, 0], -1)) | (stats["last_within"] > 0)
    else:
        repeated = jnp.zeros((b,), bool)
    history = state.prev_actions
    if history.shape[1]:
        history = jnp.concatenate([history[:, 1:], actions[:, None].astype(jnp.float32)], 1)
    new = HybridState(
        prev_actions=history,
        prev_lin_vel=kin.lin_vel.astype(jnp.float32), boundary=boundary,
        skips=jnp.where(skip, state.skips + 1, 0),
        last_whole=jnp.where(skip, state.last_whole, whole),
        repeats=jnp.where(skip, state.repeats, jnp.where(repeated, state.repeats + 1, 0)),
        recent=jnp.concatenate([tokens[:, None], state.recent], 1)[:, : hcfg.recent_candidates],
        recent_valid=jnp.concatenate([jnp.ones((b, 1), bool), state.recent_valid], 1)[:, : hcfg.recent_candidates],
        budget=bstate)
    stats = dict(stats, metric=metric, drafter_mode=(~use_retrieval).astype(jnp.float32))
    return actions, tokens, new, stats
