"""Batch-aware draft budgets: per control step, choose the draft budget that
minimises the expected time per action, from a cost table measured on the device in use
(`heisd_jax.cost_model`) and running estimates of the acceptance seen so far. Our design;
HeiSD and Spec-VLA use one fixed budget.

Options (`options`): plain AR (no drafting at all); `ar+retrieval`, the candidates verified
inside the prefill for the rows in retrieval mode and the rest of each action decoded by
single-token target passes (`HybridConfig.continuation="ar"`: no drafter at all; its
"rounds" are those passes); and, for every draft tree of the grid (`BudgetConfig.trees`),
drafter SD from the prefill alone, or after the candidates verified inside the prefill
(HeiSD). The choice is
batch-wide, a `lax.switch` over compiled branches: the rows of a batch advance in lockstep,
so a batch pays its prefill plus its *largest* number of draft rounds, whatever the others.

Predicted time of option o: `fixed_ms[o] + rounds[o] * round_ms[o]`:
  - `fixed_ms`, `round_ms` (`Costs`, measured at the batch size in use): one draft-verify
    round of o's tree, and everything else of one action (prefill with or without the
    candidates' block, the drafter's prompt pass, the hand-over); AR: its whole decode;
  - `rounds[o]` (`BudgetState`): a running estimate (exponential moving average) of the
    batch's draft rounds per action under o, updated whenever o runs (`ar+retrieval` also
    whenever a tree after the candidates runs: the accepted prefix fixes its passes; a step
    where every row skips updates nothing). Options start from
    the fewest rounds their tree allows (0 with retrieval: a whole accepted candidate;
    ceil(6 / (depth + 1)) without), so every option that could win gets tried once; one
    that cannot beat AR even then (`dominated`) never runs.
Retries with a bounded cost: an option predicted slower than the best by `regret` ms is
re-tried once the time elapsed since it last ran, `idle_ms`, reaches regret / retry_share
(`BudgetConfig.retry_share`), so re-trying each option costs at most that share of the time
(as far as the table predicts), however many steps run, and a change of regime is still
noticed. A retry's observation counts with weight `retry_weight` (its old estimate is stale).
Forgetting a phase: each option also keeps the plain mean of every batch's rounds it has
run (`BudgetState.mean_rounds`); while an option is not chosen, its running estimate returns
towards that long-run mean by `forget` per step. A few slow steps (fine manipulation in
every row, say) make the estimate pessimistic and AR takes over; without forgetting, the
option would stay unchosen until its retry came due, about regret / retry_share ms later
(~80 steps at batch 1 on an H200, half an episode), although the phase had passed. With
it, an option whose long run beats AR comes back after about 1 / forget steps; one whose
long run loses stays where it is (the mean is no better than its estimate).
A margin: a drafting option is chosen only if predicted `margin` (10%) faster than AR. The
table's own error is of that size: at batch 16 on an H200, without a margin, the chooser
picked drafting on about half the steps although drafting measured 7-8% slower than AR in
the same replays, and two calibrations of AR's decode at batch 1 differed by 12%. The
price: at batch 1 AR runs on a quarter of the steps. The same margin lies between tree
sizes: a larger tree must be predicted `margin` faster than the next smaller one (the
second size, then, (1 + margin)^2 faster than AR). Two trees after the candidates often
cost within a few percent of each other, and without it the choice between them follows
the noise of their running estimates (on the 7B expansion's table, moving one entry by
0.05 ms moved the 8x4x32 tree's share of a replay from 3 % to 11 %, each of its steps
~1.4 ms dearer than 4x2x8's). `experiments/studies/budget_sim.py` replays the chooser on
measured cost tables; `experiments/studies/budget_replay.py` on measured per-step rounds
(`--jitter`: with the table's error).
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
    mode: str = "auto"  # "auto": choose per step; "fixed": the HybridConfig's one tree, always
    trees: tuple[tuple[int, int, int], ...] = DEFAULT_TREES
    decay: float = 0.1  # weight of a new observation in the running estimate of rounds
    retry_share: float = 0.002  # per option, at most this share of the time goes to re-trying it
    retry_weight: float = 0.5  # weight of a retry's observation (the option's estimate is stale)
    forget: float = 0.05  # per unchosen step, share by which an estimate returns to its long-run mean (0: never)
    margin: float = 0.1  # a drafting option must be predicted this much faster than AR, a larger tree than a smaller
    max_batch: int = 1  # drafting runs at batch sizes (rows per device) up to this; above, plain AR (`drafts_at`)

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
        if (not 0 < self.decay <= 1 or not 0 < self.retry_weight <= 1 or not 0 <= self.retry_share < 1
                or not 0 <= self.forget <= 1 or not 0 <= self.margin < 1):
            raise ValueError(f"need 0 < decay <= 1, 0 < retry_weight <= 1, 0 <= retry_share < 1, 0 <= forget <= 1 and "
                             f"0 <= margin < 1, got {self.decay}, {self.retry_weight}, {self.retry_share}, "
                             f"{self.forget}, {self.margin}")
        if self.max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {self.max_batch}")

    def drafts_at(self, batch: int) -> bool:
        """Whether budget "auto" may draft at this batch size (rows per device). A batch
        advances in lockstep and pays for its slowest row's passes, so drafting gains least
        where rows are many (docs/method.md has the measurements behind the default): above
        `max_batch` the method is plain AR, with no cost table needed."""
        return batch <= self.max_batch


@dataclasses.dataclass(frozen=True)
class Option:
    tree: tuple[int, int, int] | None  # None: no drafter (AR passes after the prefill)
    retrieval: bool = False  # verify the retrieved candidates (rows in retrieval mode)

    @property
    def name(self) -> str:
        base = "ar" if self.tree is None else "x".join(map(str, self.tree))
        return base + ("+retrieval" if self.retrieval else "")

    @property
    def prior_rounds(self) -> float:
        if self.tree is None or self.retrieval:
            return 0.0
        return float(math.ceil((ACTION_DIM - 1) / (self.tree[1] + 1)))


def options(cfg: BudgetConfig, mode: str) -> tuple[Option, ...]:
    """AR (always option 0); AR after the candidates verified in the prefill (unless mode is
    'drafter'); then per tree: drafter only (unless mode is 'retrieval'), with retrieval
    (unless mode is 'drafter'). `mode`: the HybridConfig's (hybrid, retrieval, drafter)."""
    out = [Option(None)]
    if mode != "drafter":
        out.append(Option(None, True))
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
    """Per option, its compiled branch: 0 = AR, then 1 = AR after verified candidates (if an
    option), then one per tree (shared by both retrieval flags)."""
    first_tree = 2 if Option(None, True) in opts else 1
    return np.asarray([int(o.retrieval) if o.tree is None else first_tree + trees.index(o.tree) for o in opts],
                      np.int32)


@struct.dataclass
class Costs:
    """What the chooser reads (from `cost_model.CostTable.costs()`), per option."""
    fixed_ms: jnp.ndarray  # [O]
    round_ms: jnp.ndarray  # [O]


@struct.dataclass
class BudgetState:
    rounds: jnp.ndarray  # [O] running estimate of the batch's draft rounds per action
    runs: jnp.ndarray  # [O] steps each option ran
    idle_ms: jnp.ndarray  # [O] time spent (as the table predicts it) since each option last ran
    mean_rounds: jnp.ndarray  # [O] mean of the batch's rounds over all of each option's runs (prior until one)


def init_state(opts: tuple[Option, ...]) -> BudgetState:
    prior = jnp.asarray([o.prior_rounds for o in opts], jnp.float32)
    zeros = jnp.zeros((len(opts),), jnp.float32)
    return BudgetState(rounds=prior, runs=zeros, idle_ms=zeros, mean_rounds=prior)


def _handicap(opts: tuple[Option, ...], margin: float) -> jnp.ndarray:
    """[O] factor on each option's predicted time: 1 for AR, 1 + margin for `ar+retrieval` and
    the smallest tree, and another factor 1 + margin per larger tree size (total tokens): a
    larger tree is chosen only when predicted `margin` faster than the next smaller one."""
    sizes = sorted({o.tree[2] for o in opts if o.tree is not None})
    steps = [0 if i == 0 else 1 + (sizes.index(o.tree[2]) if o.tree is not None else 0) for i, o in enumerate(opts)]
    return jnp.asarray((1.0 + margin) ** np.asarray(steps, np.float64), jnp.float32)


def dominated(costs: Costs, opts: tuple[Option, ...], margin: float = 0.0) -> jnp.ndarray:
    """[O] options that cannot beat plain AR (option 0) by their margin (`_handicap`) even
    with the fewest rounds their tree allows: never worth a try. (At batch 1,024 on an H200
    the retrieval options' fixed part alone exceeds AR's whole decode; their first tries cost
    1% of a 160-step replay.)"""
    best_case = costs.fixed_ms + jnp.asarray([o.prior_rounds for o in opts], jnp.float32) * costs.round_ms
    return (best_case * _handicap(opts, margin) >= costs.fixed_ms[0]) & (jnp.arange(len(opts)) > 0)


def only_ar(costs: Costs, opts: tuple[Option, ...], margin: float = 0.0) -> bool:
    """Whether every option but AR is `dominated`: the chooser would run AR on every step, and
    the per-step work around it (the boundary, the keys, the choice, verify-skip) would only
    add time (at large batch sizes the prefill alone is most of AR's decode). Evaluated on the
    host, once per cost table."""
    return bool(np.all(np.asarray(dominated(costs, opts, margin))[1:]))


def predicted_ms(costs: Costs, state: BudgetState, opts: tuple[Option, ...], any_retrieval,
                 margin: float = 0.0) -> jnp.ndarray:
    """Expected ms per action of each option [O], drafting options' times raised by `margin`
    (inf where not eligible this step, or never: `dominated`)."""
    pred = (costs.fixed_ms + state.rounds * costs.round_ms) * _handicap(opts, margin)
    needs = jnp.asarray([o.retrieval for o in opts])
    return jnp.where((needs & ~any_retrieval) | dominated(costs, opts, margin), jnp.inf, pred)


def choose(costs: Costs, state: BudgetState, opts: tuple[Option, ...], any_retrieval,
           retry_share: float = 0.0, margin: float = 0.0) -> jnp.ndarray:
    """The option with the least expected time per action (ties: the earlier, AR first; a
    drafting option's time counted `margin` higher, a larger tree's once more per size),
    unless a slower option is due for a retry: idle for at least regret / retry_share ms
    (then the most overdue one)."""
    pred = predicted_ms(costs, state, opts, any_retrieval, margin)
    best = jnp.argmin(pred)
    regret = pred - pred[best]
    due = jnp.isfinite(pred) & (regret > 0) & (retry_share * state.idle_ms >= regret)
    overdue = jnp.where(due, retry_share * state.idle_ms - regret, -jnp.inf)
    return jnp.where(jnp.any(due), jnp.argmax(overdue), best).astype(jnp.int32)


def update(cfg: BudgetConfig, state: BudgetState, opts: tuple[Option, ...], costs: Costs, chosen,
           rounds, ar_retrieval_rounds=-1.0) -> BudgetState:
    """After option `chosen` ran and the batch needed `rounds` draft rounds: its estimate
    moves towards `rounds` (replaced on its first run, weight `retry_weight` after idling,
    else `decay`) and its long-run mean takes the observation in; every other option's
    estimate returns towards its long-run mean by `forget` (options never run keep their
    prior), and its idle time grows by this step's predicted time.

    `ar_retrieval_rounds` (>= 0 where known): the rounds `ar+retrieval` would have needed on
    this step. Every option that verifies the candidates accepts the same prefix of them, and
    `ar+retrieval` then needs one single-token pass per token left after the prefill's own
    (`hybrid.decode_auto` counts them), so a step run by a tree after the candidates observes
    `ar+retrieval` too, as if it had run. Learnt only on the steps it is chosen, which are
    those where its estimate is low, `ar+retrieval`'s estimate would be biased low: its
    outcome is all or little (no rounds when a candidate is accepted whole, up to six
    passes when none is), so a few whole acceptances would make it look cheapest, and the
    next miss cost six passes."""
    hit = jnp.arange(len(opts)) == chosen
    is_ar_retrieval = jnp.asarray([o.tree is None and o.retrieval for o in opts])
    seen = hit | (is_ar_retrieval & (jnp.asarray(ar_retrieval_rounds) >= 0))
    observed = jnp.where(hit, rounds, ar_retrieval_rounds)
    weight = jnp.where(state.runs == 0, 1.0, jnp.where(state.idle_ms > 0, cfg.retry_weight, cfg.decay))
    ran = state.rounds + weight * (observed - state.rounds)
    idle = state.rounds + cfg.forget * (state.mean_rounds - state.rounds)
    runs = state.runs + seen
    mean = jnp.where(seen, state.mean_rounds + (observed - state.mean_rounds) / jnp.maximum(runs, 1.0),
                     state.mean_rounds)
    step_ms = costs.fixed_ms[chosen] + rounds * costs.round_ms[chosen]
    return BudgetState(rounds=jnp.where(seen, ran, idle), runs=runs,
                       idle_ms=jnp.where(seen, 0.0, state.idle_ms + step_ms), mean_rounds=mean)


def simulate(cfg: BudgetConfig, costs: Costs, opts: tuple[Option, ...], true_rounds, steps: int,
             any_retrieval: bool = True) -> tuple[np.ndarray, float]:
    """The chooser over `steps` steps where option o always needs true_rounds[o] draft rounds
    and costs what the table predicts for them: (runs per option, total ms). The arithmetic
    behind the retry bound (tests/test_budget.py, experiments/studies/budget_sim.py), on the host."""
    true_ms = np.asarray(costs.fixed_ms) + np.asarray(true_rounds) * np.asarray(costs.round_ms)
    state, spent = init_state(opts), 0.0
    for _ in range(steps):
        o = int(choose(costs, state, opts, jnp.asarray(any_retrieval), cfg.retry_share, cfg.margin))
        spent += float(true_ms[o])
        state = update(cfg, state, opts, costs, o, float(true_rounds[o]))
    return np.asarray(state.runs), spent


def simulate_recorded(cfg: BudgetConfig, costs: Costs, opts: tuple[Option, ...], rounds: dict,
                      horizon: int = 0, prices: Costs | None = None) -> tuple[np.ndarray, dict]:
    """The chooser over recorded steps, started afresh every `horizon` steps (0: never): (ms
    per step as `prices` (default: the chooser's own table, `costs`) prices each choice, 0 on
    skipped steps; choices per option name). A chooser given a perturbed table and priced by
    the measured one shows what the table's error costs.
    `rounds`: per step, 'skipped' and 'drafter' (bool: no target pass; a drafter-mode step, where no option needs
    retrieval), and the draft rounds of 'ar+retrieval' and of each tree by name (after the
    candidates on retrieval steps, from the prefill on drafter steps), as replaying each option
    alone measures them (experiments/studies/budget_replay.py); a retrieval step run by a tree
    after the candidates observes 'ar+retrieval''s rounds too, as the decoder does. A tree from the prefill alone
    on a retrieval step, which no replay measures, is priced at its mean on drafter steps (its
    prior where none was recorded); plain AR needs no rounds. On the host."""
    prices = costs if prices is None else prices
    fixed, per_round = np.asarray(prices.fixed_ms), np.asarray(prices.round_ms)
    drafter = np.asarray(rounds["drafter"], bool)
    drafter_mean = {o.name: float(np.mean(np.asarray(rounds[o.name])[drafter])) if drafter.any() else o.prior_rounds
                    for o in opts if o.tree is not None and not o.retrieval}
    state, chosen = init_state(opts), {o.name: 0 for o in opts}
    spent = np.zeros(len(rounds["skipped"]))
    for t in range(len(rounds["skipped"])):
        if horizon and t % horizon == 0:
            state = init_state(opts)
        if rounds["skipped"][t]:
            continue
        retrieval_step = not drafter[t]
        o = int(choose(costs, state, opts, np.asarray(retrieval_step), cfg.retry_share, cfg.margin))
        opt = opts[o]
        if opt.tree is None:
            r = float(rounds["ar+retrieval"][t]) if opt.retrieval else 0.0
        elif opt.retrieval or not retrieval_step:
            r = float(rounds[opt.name.removesuffix("+retrieval")][t])
        else:
            r = drafter_mean[opt.name]
        spent[t] = float(fixed[o] + r * per_round[o])
        chosen[opt.name] += 1
        seen_ar = opt.retrieval and retrieval_step and "ar+retrieval" in rounds
        state = update(cfg, state, opts, costs, o, r, float(rounds["ar+retrieval"][t]) if seen_ar else -1.0)
    return spent, chosen
