"""Batch-aware draft budgets (issue 9): per control step, choose the draft budget that
minimises the expected time per action, from a cost table measured on the device in use
(`heisd_jax.cost_model`) and running estimates of the acceptance seen so far. Our design;
HeiSD and Spec-VLA use one fixed budget.

Options (`options`): plain AR (no drafting at all) and, for every draft tree of the grid
(`BudgetConfig.trees`), drafter SD from the prefill alone, or with the retrieved candidates
verified inside the prefill for the rows in retrieval mode (HeiSD). The choice is
batch-wide, a `lax.switch` over compiled branches: the rows of a batch advance in lockstep,
so a batch pays its prefill plus its *largest* number of draft rounds, whatever the others.

Predicted time of option o: `fixed_ms[o] + rounds[o] * round_ms[o]`:
  - `fixed_ms`, `round_ms` (`Costs`, measured at the batch size in use): one draft-verify
    round of o's tree, and everything else of one action (prefill with or without the
    candidates' block, the drafter's prompt pass, the hand-over); AR: its whole decode;
  - `rounds[o]` (`BudgetState`): a running estimate (exponential moving average) of the
    batch's draft rounds per action under o, updated whenever o runs. Options start from
    the fewest rounds their tree allows (0 with retrieval: a whole accepted candidate;
    ceil(6 / (depth + 1)) without), so every option that could win gets tried, and the
    estimates of options not chosen drift back towards that optimistic prior
    (`BudgetConfig.explore`), so a change of regime is noticed.
An option that needs retrieval rows is not eligible on a step where no row verifies
retrieval (it would run as its drafter-only twin).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from flax import struct

from heisd_jax import spec_decode
from heisd_jax.tokenizer import ACTION_DIM

BUDGETS = ("auto", "fixed")
DEFAULT_TREES = ((4, 2, 8), (8, 4, 32))  # (top_k, depth, total_tokens)


def parse_trees(text: str) -> tuple[tuple[int, int, int], ...]:
    """'4x2x8/8x4x32' -> ((4, 2, 8), (8, 4, 32))."""
    out = []
    for part in filter(None, text.split("/")):
        try:
            k, d, n = (int(v) for v in part.split("x"))
        except ValueError as e:
            raise ValueError(f"draft tree {part!r} is not TOPKxDEPTHxTOTAL (e.g. 4x2x8)") from e
        out.append((k, d, n))
    if not out:
        raise ValueError(f"no draft tree in {text!r}; write e.g. 4x2x8/8x4x32")
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class BudgetConfig:
    mode: str = "fixed"  # "auto": choose per step; "fixed": the HybridConfig's one tree, always
    trees: tuple[tuple[int, int, int], ...] = DEFAULT_TREES
    decay: float = 0.1  # weight of a new observation in the running estimate of rounds
    explore: float = 0.01  # per step, unchosen options' estimates move this far towards their prior

    def __post_init__(self):
        if self.mode not in BUDGETS:
            raise ValueError(f"unknown budget {self.mode!r}; valid: {', '.join(BUDGETS)}")
        if not self.trees:
            raise ValueError("the budget needs at least one draft tree")
        if len(set(self.trees)) != len(self.trees):
            raise ValueError(f"draft trees repeat: {self.trees}")
        for k, d, n in self.trees:
            if k < 1 or d < 1 or not 1 <= n <= k * d:
                raise ValueError(f"draft tree {k}x{d}x{n}: need top_k >= 1, depth >= 1, 1 <= total <= top_k*depth")
        if not 0 < self.decay <= 1 or not 0 <= self.explore < 1:
            raise ValueError(f"need 0 < decay <= 1 and 0 <= explore < 1, got {self.decay}, {self.explore}")


@dataclasses.dataclass(frozen=True)
class Option:
    tree: tuple[int, int, int] | None  # None: plain AR
    retrieval: bool = False  # verify the retrieved candidates (rows in retrieval mode)

    @property
    def name(self) -> str:
        if self.tree is None:
            return "ar"
        return "x".join(map(str, self.tree)) + ("+retrieval" if self.retrieval else "")

    @property
    def prior_rounds(self) -> float:
        if self.tree is None or self.retrieval:
            return 0.0
        return float(math.ceil((ACTION_DIM - 1) / (self.tree[1] + 1)))


def options(cfg: BudgetConfig, mode: str) -> tuple[Option, ...]:
    """AR (always option 0), then per tree: drafter only (unless mode is 'retrieval'), with
    retrieval (unless mode is 'drafter'). `mode`: the HybridConfig's (hybrid, retrieval, drafter)."""
    out = [Option(None)]
    for tree in cfg.trees:
        if mode != "retrieval":
            out.append(Option(tree, False))
        if mode != "drafter":
            out.append(Option(tree, True))
    return tuple(out)


def tree_spec(spec: spec_decode.SpecConfig, tree: tuple[int, int, int]) -> spec_decode.SpecConfig:
    """`spec` (acceptance rule) with the tree shape of a budget option."""
    k, d, n = tree
    return dataclasses.replace(spec, top_k=k, depth=d, total_tokens=n)


def branch_index(opts: tuple[Option, ...], trees: tuple) -> np.ndarray:
    """Per option, its compiled branch: 0 = AR, 1 + i = tree i (shared by both retrieval flags)."""
    return np.asarray([0 if o.tree is None else 1 + trees.index(o.tree) for o in opts], np.int32)


@struct.dataclass
class Costs:
    """What the chooser reads (from `cost_model.CostTable.costs()`), per option."""
    fixed_ms: jnp.ndarray  # [O]
    round_ms: jnp.ndarray  # [O]


@struct.dataclass
class BudgetState:
    rounds: jnp.ndarray  # [O] running estimate of the batch's draft rounds per action
    runs: jnp.ndarray  # [O] steps each option ran


def init_state(opts: tuple[Option, ...]) -> BudgetState:
    return BudgetState(rounds=jnp.asarray([o.prior_rounds for o in opts], jnp.float32),
                       runs=jnp.zeros((len(opts),), jnp.float32))


def predicted_ms(costs: Costs, state: BudgetState, opts: tuple[Option, ...], any_retrieval) -> jnp.ndarray:
    """Expected ms per action of each option [O] (inf where not eligible this step)."""
    pred = costs.fixed_ms + state.rounds * costs.round_ms
    needs = jnp.asarray([o.retrieval for o in opts])
    return jnp.where(needs & ~any_retrieval, jnp.inf, pred)


def choose(costs: Costs, state: BudgetState, opts: tuple[Option, ...], any_retrieval) -> jnp.ndarray:
    """The option with the least expected time per action (ties: the earlier, AR first)."""
    return jnp.argmin(predicted_ms(costs, state, opts, any_retrieval)).astype(jnp.int32)


def update(cfg: BudgetConfig, state: BudgetState, opts: tuple[Option, ...], chosen, rounds) -> BudgetState:
    """After option `chosen` ran and the batch needed `rounds` draft rounds."""
    prior = jnp.asarray([o.prior_rounds for o in opts], jnp.float32)
    hit = jnp.arange(len(opts)) == chosen
    seen = (1 - cfg.decay) * state.rounds + cfg.decay * rounds
    first = state.runs == 0  # the first observation replaces the prior outright
    ran = jnp.where(first, rounds, seen)
    drift = state.rounds + cfg.explore * (prior - state.rounds)
    return BudgetState(rounds=jnp.where(hit, ran, drift), runs=state.runs + hit)
