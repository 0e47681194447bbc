"""The measured cost model behind `budget="auto"`: latencies of the target's and
the drafter's passes, and of each budget option's round and fixed part, measured on the
device in use at the batch size in use, cached on disk.

Every latency is an *in-graph* cost (`heisd_jax.timing.in_graph_ms`): the piece looped n1
and n2 times inside one jitted program, the difference over n2 - n1, so the dispatch per
jitted call (which a real decode pays once per action, not per pass) is not counted per
pass; the median over back-to-back pairs.

An option's cost is `fixed + rounds x round` (budget.Costs). A draft round can cost more inside
the decode's `while_loop` than alone (experiments/studies/bench_round.py), so for a tree
with a retrieval option both are read off whole decodes: the decode with candidates equal
to the target's own greedy action (accepted whole: zero rounds) is the fixed part, and the
slope to the decode on random inputs (which need several rounds) is the round's cost in
context. (At large batches some row may still need rounds there: f32 matmuls run as TF32
on GPUs and a near-tie argmax can differ between the fused prefill and AR's passes; at
batch 1,024 on an H200 the anchor ran 3 rounds. Its measured rounds are subtracted.) The
tree's drafter-only option shares that round cost; its fixed part is the median over
random input draws of (decode - rounds x round). Without a retrieval option,
the round measured alone is used. (Subtracting rounds measured alone instead over-predicts
the fixed part: at batch 16 on an H100, 2.4-3.1 ms against a 0.92 ms prefill.)

Calibrate on an otherwise idle device: a table measured while other programs share the GPU
is wrong (seen: a drafter pass "costing" 0 ms and a retrieval option 2x its real cost), and
it stays cached; delete the file (or pass another cache directory) to measure again.

A table is tied to its key (device, platform, jax version, the model's architecture, dtype,
matmul precision, batch size, options, number of candidates): costs depend on the shapes, not
on the weights' values, so a retrained model of the same architecture shares its table, and a
7B expansion's key costs nothing to compute. `load_cached` reads the cached file only if its key
equals the current one, or, where none is, a table whose key differs only in holding more draft
trees, cut down to this key's (`subset`: each option is its own measured program). Measuring
is always asked for explicitly (`load_or_calibrate(..., measure=True)`, the entry points'
--calibrate_costs): a method never spends minutes calibrating behind a user's back.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from heisd_jax import budget, cache_dirs, drafter, hybrid, results_io, retrieval, spec_decode, target_model, vla
from heisd_jax.timing import in_graph, in_graph_ms
from heisd_jax.tokenizer import ACTION_DIM, N_BINS

FORMAT = 5  # 5: keyed by the model's architecture (4: weight fingerprints); older tables are re-measured
DEFAULT_CACHE = cache_dirs.cache_root() / "costs"


def synthetic_inputs(cfg: vla.VLAConfig, batch: int, n_candidates: int, seed: int = 0):
    """Random observations and retrieved candidates of the right shapes (costs do not depend
    on the values; acceptance, which does, is estimated online by `budget`)."""
    rng = np.random.default_rng(seed)
    obs = vla.Observation(
        image=jnp.asarray(rng.integers(0, 256, (batch, *cfg.image_shape)), jnp.uint8),
        instruction=jnp.asarray(rng.integers(1, cfg.text_vocab, (batch, cfg.text_len)), jnp.int32),
        proprio=jnp.asarray(rng.normal(size=(batch, cfg.proprio_dim)), jnp.float32))
    cand = jnp.asarray(rng.integers(0, N_BINS, (batch, n_candidates, ACTION_DIM)) + cfg.first_action_id, jnp.int32)
    return obs, cand


def _non_default(cfg: vla.VLAConfig, fields: tuple[str, ...]) -> dict:
    """`fields` of cfg that differ from VLAConfig's defaults: numerics added to the key after tables
    were cached, which leave the keys of tables measured at their defaults unchanged."""
    return {k: getattr(cfg, k) for k in fields if getattr(cfg, k) != getattr(vla.VLAConfig, k)}


def table_key(cfg: vla.VLAConfig, hcfg: hybrid.HybridConfig, batch: int) -> dict:
    dev = jax.devices()[0]
    model = cfg.architecture()
    return {"format": FORMAT, "device": dev.device_kind, "platform": dev.platform, "jax": jax.__version__,
            "model": model, "dtype": cfg.dtype, "matmul_precision": cfg.matmul_precision, "unroll": cfg.unroll,
            **_non_default(cfg, ("attention", "patchify")), "batch": int(batch),
            "n_candidates": hcfg.n_candidates,
            "recent_candidates": hcfg.recent_candidates, "verify": hcfg.verify,
            "options": [o.name for o in budget.options(hcfg.budget, hcfg.mode)]}


@dataclasses.dataclass
class CostTable:
    key: dict
    options: list[str]
    fixed_ms: list[float]  # per option (see budget)
    round_ms: list[float]
    decode_ms: list[float]  # the option's whole decode on the calibration inputs (median over draws)
    decode_rounds: list[float]  # ... and the draft rounds it needed there (median)
    pieces: dict  # prefill_ms {appended tokens: ms}, cached_ms {T: ms}, query_ms, round_alone_ms, zero_round_ms
    # (with calibrate(detail=True) also the drafter's: drafter_ms {T: ms}, drafter_prompt_ms)
    seconds: float  # how long the calibration took

    def costs(self) -> budget.Costs:
        return budget.Costs(fixed_ms=jnp.asarray(self.fixed_ms, jnp.float32),
                            round_ms=jnp.asarray(self.round_ms, jnp.float32))

    @property
    def ceiling(self) -> float:
        """AR / prefill: the most any method that still prefills every action can gain."""
        return self.decode_ms[0] / self.pieces["prefill_ms"]["0"]

    def report(self) -> str:
        p = self.pieces
        ms_list = lambda d, plus="": ", ".join(f"{plus}{k}: {v:.3f}" for k, v in d.items()) or "-"  # noqa: E731
        lines = [f"cost table: {self.key['device']}, batch {self.key['batch']}, {self.key['dtype']} "
                 f"(calibrated in {self.seconds:.1f}s)",
                 f"  prefill + appended tokens: {ms_list(p['prefill_ms'], '+')} ms",
                 f"  cached target pass over T: {ms_list(p['cached_ms'])} ms"]
        if "drafter_ms" in p:  # measured with calibrate(detail=True)
            lines.append(f"  drafter pass over T: {ms_list(p['drafter_ms'])} ms; drafter prompt pass "
                         f"{p['drafter_prompt_ms']:.3f} ms")
        lines += [f"  datastore query {p['query_ms']:.3f} ms; draft round measured alone: "
                  f"{ms_list(p['round_alone_ms'])} ms; decode with whole acceptance (0 rounds): "
                  f"{ms_list(p['zero_round_ms'])} ms",
                  f"  ceiling AR / prefill: {self.ceiling:.2f}x"]
        for i, name in enumerate(self.options):
            lines.append(f"  {name:<22} fixed {self.fixed_ms[i]:7.3f} ms + rounds x {self.round_ms[i]:6.3f} ms "
                         f"(whole decode {self.decode_ms[i]:.3f} ms at {self.decode_rounds[i]:.0f} rounds)")
        return "\n".join(lines)


def calibrate(params, model: target_model.Model, hcfg: hybrid.HybridConfig, batch: int, reps: int = 7,
              n_draws: int = 3, detail: bool = False) -> CostTable:
    """Measures the cost table: each option's whole decode on `n_draws` random input draws,
    and the pieces the table is read from (the prefill, a single-token pass, the datastore
    query, each tree's round measured alone). One compile per measured program, which is
    what the calibration's time is: seconds for the shipped target, minutes for a 7B
    expansion. `detail` also measures the pass costs the table only reports (the prefill with
    appended candidates, cached passes over 2-33 tokens, the drafter's passes): twice the
    compiles. model: a `vla.VLAConfig` or any `target_model.TargetModel`."""
    target = target_model.as_target(model)
    cfg = target.cfg
    t_start = time.perf_counter()
    tp, dp = params["target"], params["drafter"]
    n = hcfg.n_verified  # the datastore's candidates and the recent actions
    obs, cand = synthetic_inputs(cfg, batch, n)
    valid = jnp.ones(cand.shape[:2], bool)
    ms = lambda fn, *args: in_graph_ms(fn, args, reps=reps)  # noqa: E731

    prefill_ms, prefilled = in_graph(lambda tp, obs: target.prefill(tp, obs), (tp, obs), reps=reps)
    _, hidden, x, cache = prefilled
    pieces = {"prefill_ms": {"0": prefill_ms}, "cached_ms": {}}

    def cached_ms(t):
        toks = jnp.full((batch, t), cfg.first_action_id, jnp.int32)
        depth = jnp.broadcast_to(jnp.arange(t), (batch, t))
        intra = jnp.broadcast_to(jnp.tril(jnp.ones((t, t), bool)), (batch, t, t))
        pieces["cached_ms"][str(t)] = ms(lambda tp, c, a, b, i: target.cached_pass(tp, c, a, b, i)[0],
                                         tp, cache, toks, depth, intra)
    cached_ms(1)  # the round of AR after the verified candidates, before its slope is measured
    if detail:
        for m in sorted({1, n}):
            block = hybrid.candidate_block(cand[:, :m])
            pieces["prefill_ms"][str(m * (ACTION_DIM - 1))] = ms(
                lambda tp, obs, block: target.prefill_with_block(tp, obs, *block)[3], tp, obs, block)
        largest = max(t[2] for t in hcfg.budget.trees) + 1
        for t in sorted({t for t in (2, 4, 8, 16, 32) if t < largest} | {largest}):
            cached_ms(t)
        key_ok = vla.prompt_key_mask(cfg, obs.instruction)
        root_emb = target.embed_tokens(tp, jnp.full((batch,), cfg.first_action_id, jnp.int32))
        pieces["drafter_prompt_ms"], (_, dcache) = in_graph(
            lambda dp, x, h, k, e: drafter.prompt_pass(dp, cfg, x, h, k, e), (dp, x, hidden, key_ok, root_emb),
            reps=reps)
        pieces["drafter_ms"] = {}
        for t in sorted({k for k, _, _ in hcfg.budget.trees} | {ACTION_DIM}):
            emb = jnp.zeros((batch, t, cfg.d_model), cfg.dtype)
            pos = jnp.broadcast_to(cfg.prompt_len + jnp.arange(t), (batch, t))
            mask = jnp.ones((batch, t, cfg.cache_slots), bool)
            pieces["drafter_ms"][str(t)] = ms(
                lambda dp, c, e, p, m: drafter.cached_pass(dp, cfg, c, e, e, p, c.length, m)[0], dp, dcache, emb, pos,
                mask)

    query_ms = 0.0  # every option but plain AR queries the datastore first
    if "store" in params and hcfg.n_candidates:
        keys = jnp.zeros((batch, params["store"].keys.shape[1]), jnp.float32)
        query_ms = ms(lambda st, k: retrieval.query(st, k, jnp.zeros((batch,), jnp.int32), hcfg.n_candidates)[1], params["store"], keys)
    pieces["query_ms"] = query_ms
    opts = budget.options(hcfg.budget, hcfg.mode)
    draws = [(obs, cand)] + [synthetic_inputs(cfg, batch, n, seed) for seed in range(1, n_draws)]
    whole = lambda fn, *args: in_graph(fn, args, n=(1, 4), reps=reps)  # noqa: E731  (whole decodes: fewer calls)
    skip = jnp.zeros((batch,), bool)
    def ar(tp, obs):
        return target_model.ar_decode(tp, target, obs)[0]
    ar_ms, ar_tokens = whole(ar, tp, obs)
    # Candidates equal to the target's own greedy action: accepted whole, zero draft rounds.
    exact = jnp.broadcast_to(ar_tokens[:, None], cand.shape)
    rows = {"ar": (ar_ms, 0.0, ar_ms, 0.0)}  # option -> (fixed, round, whole decode, its rounds)
    pieces["round_alone_ms"], pieces["zero_round_ms"] = {}, {}

    def decoder(hc):
        def dec(p, obs, cand, valid, use, skip):
            return hybrid.decode(p, target, hc, obs, cand, valid, use, skip)

        def timed(use, inputs):
            runs = [whole(dec, params, ob, ca, valid, use, skip) for ob, ca in inputs]
            return (np.array([t for t, _ in runs]),
                    np.array([float(jnp.max(out[1]["rounds"])) for _, out in runs]))
        return timed

    def row(fixed, round_ms, t, r):
        """(fixed, round, whole decode, its rounds); a fixed part is never below the prefill,
        and every drafting option queries the datastore first."""
        return max(fixed, pieces["prefill_ms"]["0"]) + query_ms, round_ms, t, r

    def in_context(timed, name, round_ms):
        """Fixed part and round cost of a retrieval option from its whole decodes: the
        zero-round anchor (candidates accepted whole) and the slope to random candidates."""
        (t0,), (r0,) = timed(jnp.ones((batch,), bool), [(obs, exact)])
        pieces["zero_round_ms"][name] = float(t0)
        t, r = map(np.median, timed(jnp.ones((batch,), bool), draws))
        if r - r0 >= 1 and t > t0:
            round_ms = float((t - t0) / (r - r0))
        return float(t0 - r0 * round_ms), round_ms, float(t), float(r)

    ar_retrieval = budget.Option(None, True)
    if ar_retrieval in opts:  # the candidates verified in the prefill, then AR passes (no drafter)
        rows[ar_retrieval.name] = row(*in_context(decoder(dataclasses.replace(hcfg, continuation="ar")),
                                                  ar_retrieval.name, pieces["cached_ms"]["1"]))
    for tree in dict.fromkeys(o.tree for o in opts if o.tree is not None):
        spec = budget.tree_spec(hcfg.spec, tree)
        timed = decoder(dataclasses.replace(hcfg, spec=spec, continuation="drafter"))
        s0 = jax.jit(lambda tp, dp, pre, obs, spec=spec: spec_decode.start(
            tp, dp, target, *pre, obs, slack=spec.depth + 1))(tp, dp, prefilled, obs)
        name = budget.Option(tree, False).name
        # The whole state out (not just the tokens), or XLA drops the cache commit.
        round_ms = pieces["round_alone_ms"][name] = ms(
            lambda tp, dp, s, spec=spec: spec_decode.round_step(tp, dp, target, spec, s), tp, dp, s0)
        mine = [o for o in opts if o.tree == tree]
        if any(o.retrieval for o in mine):  # the round's cost in context: slope from the zero-round anchor
            rows[name + "+retrieval"] = row(*in_context(timed, name + "+retrieval", round_ms))
            round_ms = rows[name + "+retrieval"][1]
        if any(not o.retrieval for o in mine):
            t, r = timed(jnp.zeros((batch,), bool), draws)
            rows[name] = row(float(np.median(t - r * round_ms)), round_ms, float(np.median(t)), float(np.median(r)))
    fixed, rnd, decode_ms, nrounds = (list(col) for col in zip(*(rows[o.name] for o in opts)))
    return CostTable(key=table_key(cfg, hcfg, batch), options=[o.name for o in opts], fixed_ms=fixed,
                     round_ms=rnd, decode_ms=decode_ms, decode_rounds=nrounds, pieces=pieces,
                     seconds=time.perf_counter() - t_start)


def cache_file(directory: str | Path, key: dict) -> Path:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return Path(directory) / f"costs_{digest}.json"


class MissingCostTable(ValueError):
    """No cost table is cached for this device, model, settings and batch size."""


def _tree_of(option: str) -> str | None:
    """'4x2x8+retrieval' -> '4x2x8'; 'ar', 'ar+retrieval' -> None."""
    base = option.removesuffix("+retrieval")
    return None if base == "ar" else base


def subset(table: CostTable, key: dict) -> CostTable | None:
    """`table` cut down to `key`'s options, where `key` differs from its key only in holding
    fewer draft trees (each option of a table is measured as its own program, so its entries
    do not depend on which other trees were measured beside it); else None."""
    trees = {_tree_of(o) for o in key["options"]} - {None}
    keep = [i for i, o in enumerate(table.options) if _tree_of(o) is None or _tree_of(o) in trees]
    if ({**table.key, "options": key["options"]} != key or [table.options[i] for i in keep] != key["options"]
            or len(keep) == len(table.options)):
        return None
    pick = lambda values: [values[i] for i in keep]  # noqa: E731
    per_tree = ("round_alone_ms", "zero_round_ms")  # pieces named by option or tree
    pieces = {k: ({n: v for n, v in table.pieces[k].items() if _tree_of(n) is None or _tree_of(n) in trees}
                  if k in per_tree else v) for k, v in table.pieces.items()}
    return dataclasses.replace(table, key=key, options=list(key["options"]), fixed_ms=pick(table.fixed_ms),
                               round_ms=pick(table.round_ms), decode_ms=pick(table.decode_ms),
                               decode_rounds=pick(table.decode_rounds), pieces=pieces)


def _read(path: Path, log: Callable[[str], None]) -> CostTable | None:
    try:
        return CostTable(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as e:
        log(f"cost table {path} is unreadable ({e})")
        return None


def load_cached(cfg: vla.VLAConfig, hcfg: hybrid.HybridConfig, batch: int,
                directory: str | Path | None = DEFAULT_CACHE, log: Callable[[str], None] = print) -> CostTable | None:
    """The cached table for this key, or None (logging why: none, another key, unreadable).
    Where none is cached under this key, a table of the same key measured with more draft trees
    serves, cut down to this key's trees (`subset`): `trees=4x2x8` reads the default's table."""
    if directory is None:
        return None
    key = table_key(cfg, hcfg, batch)
    path = cache_file(directory, key)
    if not path.exists():
        for other in sorted(Path(directory).glob("costs_*.json")):
            table = _read(other, lambda _: None)
            try:
                cut = subset(table, key) if table is not None else None
            except (TypeError, KeyError, AttributeError, IndexError):  # a damaged file: not this key's
                cut = None
            if cut is not None:
                log(f"cost table from {other}, cut to {', '.join(cut.options)}")
                return cut
        return None
    table = _read(path, log)
    if table is None:
        return None
    if table.key != key or len(table.fixed_ms) != len(key["options"]):
        log(f"cost table {path} was measured for another setting ({_diff(table.key, key)})")
        return None
    log(f"cost table from {path}")
    return table


def load_or_calibrate(params, cfg: vla.VLAConfig, hcfg: hybrid.HybridConfig, batch: int,
                      directory: str | Path | None = DEFAULT_CACHE, log: Callable[[str], None] = print,
                      measure: bool = True) -> CostTable:
    """The cached table for this key; else, with `measure`, a fresh calibration (`calibrate`,
    then cached in `directory`; None: never cached), or without it `MissingCostTable`."""
    table = load_cached(cfg, hcfg, batch, directory, log)
    if table is not None:
        return table
    if not measure:
        where = f"in {directory}" if directory is not None else "(no cost cache directory given)"
        raise MissingCostTable(
            f"budget=auto needs a decode-cost table for this device, model, settings and batch size {batch}, and none "
            f"is cached {where}: rerun with --calibrate_costs to measure it now (on an idle device: about a minute "
            f"for the shipped target, several for a 7B expansion, whose every compile takes tens of seconds; cached "
            f"for later runs), or use budget=fixed")
    log(f"measuring the decode-cost table at batch {batch} (one compile per measured program: about a minute "
        f"for the shipped target, several for a 7B expansion)")
    table = calibrate(params, cfg, hcfg, batch)
    if directory is not None:
        path = cache_file(directory, table.key)
        results_io.write_json_atomic(path, dataclasses.asdict(table))
        log(f"cost table measured in {table.seconds:.1f}s, saved to {path}")
    return table


def _diff(old: dict, new: dict) -> str:
    keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    return ", ".join(f"{k}: {old.get(k)!r} != {new.get(k)!r}" for k in keys) or "same key"
