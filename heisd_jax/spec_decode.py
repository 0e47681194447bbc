"""Drafter-based speculative decoding of one action (Spec-VLA / EAGLE-2), batched and jitted.

Per row: the target's prefill gives the first action token (the *root*); then rounds of
  1. draft: an EAGLE-2 dynamic tree of `depth` levels; each level keeps the `top_k` nodes
     of highest cumulative log-probability among the children of the previous level's nodes
     (one drafter pass per level over its k nodes, with a tree attention mask); the
     `total_tokens` best nodes of the whole tree (by cumulative log-probability, which keeps
     every chosen node's ancestors) are verified;
  2. verify: one target pass over [root, chosen nodes] with an ancestor-only mask and
     position = cache length + node depth; each node is accepted if its token passes the
     acceptance rule against the target's greedy token at its parent; the deepest node whose
     whole path is accepted wins; its path is emitted plus one bonus token (the target's
     greedy token after it), and root + path are committed to the KV cache;
  3. the drafter reads the target's hidden states of the committed tokens (its own cache
     grows with them) and predicts the feature at the bonus token, the next root;
until 7 tokens exist. Every row has its own tree, acceptance and cache length; shapes are
static; rows that have their 7 tokens are masked (their state no longer changes) and the
loop (`lax.while_loop`) ends when all rows are done.

Acceptance rules: `strict` (draft == target greedy: lossless, the output equals greedy AR
decoding token for token) and `token_relaxed` (|bin(draft) - bin(greedy)| <= relax_bins,
the draft token is kept; Spec-VLA).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from heisd_jax import acceptance as rules, drafter, target_model, vla, xla_options
from heisd_jax.tokenizer import ACTION_DIM, N_BINS

ACCEPTANCE = rules.TOKEN_RULES


@dataclasses.dataclass(frozen=True)
class SpecConfig:
    top_k: int = 8
    depth: int = 4
    total_tokens: int = 32  # nodes verified per round (<= top_k * depth)
    acceptance: str = "strict"
    relax_bins: int = 0
    # token_relaxed: rank a node's children by the drafter's probability that the target's
    # choice lies within relax_bins of them, and keep them more than 2 x relax_bins apart, so
    # their acceptance windows do not overlap (`spread_children`); off: EAGLE-2's top-k bins.
    spread: bool = False

    def __post_init__(self):
        rules.check_rule(self.acceptance, rules.TOKEN_RULES)
        if self.spread and (self.acceptance != "token_relaxed" or not self.relax_bins):
            raise ValueError("spread draft trees are for token_relaxed acceptance with relax_bins >= 1")
        if not 1 <= self.top_k <= N_BINS or self.depth < 1:
            raise ValueError(f"top_k must be in 1..{N_BINS} and depth >= 1, got top_k={self.top_k} depth={self.depth}")
        if not 1 <= self.total_tokens <= self.top_k * self.depth:
            raise ValueError(f"total_tokens must be in 1..top_k*depth={self.top_k * self.depth}, got {self.total_tokens}")
        if not 0 <= self.relax_bins < N_BINS:
            raise ValueError(f"relax_bins must be in 0..{N_BINS - 1}, got {self.relax_bins}")
        if self.acceptance == "strict" and self.relax_bins:
            raise ValueError("relax_bins is only used with acceptance='token_relaxed'")

    def check_fits(self, cfg: vla.VLAConfig):
        need = cfg.prompt_len + ACTION_DIM + 1 + max(self.total_tokens, self.top_k * self.depth)
        if need > cfg.cache_slots:
            raise ValueError(f"a draft tree of {self.top_k}x{self.depth} nodes needs {need} cache slots, the model has "
                             f"{cfg.cache_slots}; lower top_k/depth")



@jax.tree_util.register_dataclass
@dataclasses.dataclass
class Tree:
    """M = depth * top_k nodes, level-major: node (l, j) at index l * top_k + j."""
    bins: jnp.ndarray  # [B, M] action bin of each node
    score: jnp.ndarray  # [B, M] cumulative log-probability
    depth: jnp.ndarray  # [M] 1..depth (root is depth 0)
    parent: jnp.ndarray  # [B, M] parent node index (-1: the root)
    anc: jnp.ndarray  # [B, M, M] bool: ancestors of each node, itself included


def draft_tree(dparams, tparams, model: target_model.Model, spec: SpecConfig, dcache: vla.KVCache,
               root_feat: jnp.ndarray) -> Tree:
    """The EAGLE-2 tree below the root. root_feat [B, D]: the drafter's feature at the
    root's position (its head gives the root's children). The root sits at position
    root_pos = dcache.length (the first uncommitted one), nodes of level l at root_pos + l;
    node g's keys/values go to scratch slot dcache.length + g. `depth - 1` drafter passes."""
    t = target_model.as_target(model)
    cfg = t.cfg
    b = root_feat.shape[0]
    k, d = spec.top_k, spec.depth
    m = k * d
    root_pos = dcache.length  # [B]
    slots = jnp.arange(cfg.cache_slots)
    prefix = vla.committed_slots(dcache)  # [B, S]

    r = spec.relax_bins if spec.spread else 0

    def children(logits):
        """[..., 256] logits -> (log-scores, bins) [..., k] of a node's k best children."""
        logp = jax.nn.log_softmax(logits)
        return spread_children(logp, k, r) if r else jax.lax.top_k(logp, k)

    score, bins = children(t.action_head(tparams, root_feat))  # level 1: [B, k]
    parent = jnp.full((b, k), -1, jnp.int32)
    all_bins, all_score, all_parent = [bins], [score], [parent]
    anc_levels = [jnp.eye(k, m, dtype=bool)[None].repeat(b, 0)]  # [B, k, M]
    feats = None
    for level in range(1, d):
        # Drafter pass over this level's k nodes: they read their parent's feature.
        parent_feat = root_feat[:, None].repeat(k, 1) if level == 1 else jnp.take_along_axis(
            feats, (all_parent[-1] - (level - 2) * k)[..., None], 1)
        emb = t.embed_tokens(tparams, all_bins[-1] + cfg.first_action_id)
        write = dcache.length + (level - 1) * k  # this level's scratch slots
        rel = slots[None] - dcache.length[:, None]  # [B, S] slot offset into the scratch area
        anc = anc_levels[-1]  # [B, k, M]
        in_tree = (rel >= 0) & (rel < m)
        tree_ok = jnp.take_along_axis(anc, jnp.clip(rel, 0, m - 1)[:, None, :].repeat(k, 1), 2) & in_tree[:, None]
        mask = prefix[:, None, :] | tree_ok
        positions = (root_pos + level)[:, None].repeat(k, 1)
        feats, dcache = drafter.cached_pass(dparams, cfg, dcache, emb, parent_feat, positions, write, mask)
        child_score, child_bins = children(t.action_head(tparams, feats))  # [B, k parents, k]
        score, flat = jax.lax.top_k((all_score[-1][..., None] + child_score).reshape(b, -1), k)
        par_local = flat // k
        bins = jnp.take_along_axis(child_bins.reshape(b, -1), flat, 1)
        node_idx = level * k + jnp.arange(k)
        all_bins.append(bins)
        all_score.append(score)
        all_parent.append(par_local + (level - 1) * k)
        anc_levels.append(jnp.take_along_axis(anc, par_local[..., None], 1) | jax.nn.one_hot(node_idx, m, dtype=bool)[None])
    depth = jnp.repeat(jnp.arange(1, d + 1), k)
    return Tree(bins=jnp.concatenate(all_bins, 1), score=jnp.concatenate(all_score, 1), depth=depth,
                parent=jnp.concatenate(all_parent, 1), anc=jnp.concatenate(anc_levels, 1))


def spread_children(logp: jnp.ndarray, k: int, r: int):
    """The k children of a node for acceptance within r bins: [..., 256] log-probabilities ->
    (scores, bins) [..., k]. A child's score is the log of the drafter's probability mass
    within r bins of it (the chance that it is accepted, were the target to choose as the
    drafter predicts); children are picked best first, each more than 2r bins from those
    before it, so no two accept the same target choice. Where fewer than k such bins exist
    the rest repeat the best with score -inf (never selected over a real node)."""
    window = jnp.ones((2 * r + 1,), logp.dtype)
    prob = jnp.exp(logp)
    mass = jax.vmap(lambda p: jnp.convolve(p, window, mode="same"))(prob.reshape(-1, N_BINS)).reshape(logp.shape)
    score = jnp.log(jnp.maximum(mass, 1e-30))
    key = mass + 1e-3 * prob  # among near-equal windows, the one centred nearest the mode
    bins_axis = jnp.arange(N_BINS)
    out_s, out_b = [], []
    for _ in range(k):
        best = jnp.argmax(key, -1)
        out_b.append(best)
        out_s.append(jnp.take_along_axis(score, best[..., None], -1)[..., 0])
        taken = jnp.abs(bins_axis - best[..., None]) <= 2 * r
        key, score = jnp.where(taken, -jnp.inf, key), jnp.where(taken, -jnp.inf, score)
    return jnp.stack(out_s, -1), jnp.stack(out_b, -1)


def select_nodes(tree: Tree, n: int) -> jnp.ndarray:
    """Indices [B, n] of the n best nodes by cumulative log-probability, ancestors first
    (a child scores below its parent: a depth penalty breaks exact ties)."""
    _, idx = jax.lax.top_k(tree.score - 1e-4 * tree.depth[None], n)
    return idx


def tree_block(model: target_model.Model, root: jnp.ndarray, tree: Tree, sel: jnp.ndarray):
    """The verification block of [root, nodes sel]: token ids [B, 1+n], depth offsets
    [B, 1+n] (position = cache length + depth) and the tree mask [B, 1+n, 1+n] (each node
    sees the root, its ancestors and itself)."""
    cfg = target_model.as_target(model).cfg
    b, n = sel.shape
    anc = jnp.take_along_axis(jnp.take_along_axis(tree.anc, sel[..., None], 1), sel[:, None, :], 2)  # [B, n, n]
    block = jnp.concatenate([root[:, None], jnp.take_along_axis(tree.bins, sel, 1) + cfg.first_action_id], 1)
    depth = jnp.concatenate([jnp.zeros((b, 1), jnp.int32), tree.depth[sel]], 1)
    intra = jnp.zeros((b, n + 1, n + 1), bool).at[:, :, 0].set(True).at[:, 1:, 1:].set(anc)
    return block, depth, intra


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class Verified:
    n_accepted: jnp.ndarray  # [B] accepted draft tokens (0..depth)
    path: jnp.ndarray  # [B, depth] block positions of the accepted path (valid: j < n_accepted)
    tokens: jnp.ndarray  # [B, depth + 1] emitted tokens: the path then the bonus (valid: j <= n_accepted)
    hidden: jnp.ndarray  # [B, depth + 1, D] target hidden of root + path (valid: j <= n_accepted)
    cache: object  # the target's cache (its own pytree) with root + path committed


def verify(tparams, model: target_model.Model, spec: SpecConfig, cache: vla.KVCache, root: jnp.ndarray, tree: Tree,
           sel: jnp.ndarray) -> Verified:
    """One target pass over [root, tree nodes sel] and the acceptance of the best path."""
    t = target_model.as_target(model)
    cfg = t.cfg
    b, n = sel.shape
    d = spec.depth
    block, depth, intra = tree_block(t, root, tree, sel)
    sel_bins, sel_depth, anc = block[:, 1:] - cfg.first_action_id, depth[:, 1:], intra[:, 1:, 1:]
    logits, hidden, blk = t.cached_pass(tparams, cache, block, depth, intra)
    greedy = jnp.argmax(vla.action_logits(cfg, logits), -1)  # [B, 1+n] bins

    # Block position of each node's parent: 0 for the root, else 1 + its index in sel.
    pos_of = jnp.zeros(tree.bins.shape, jnp.int32).at[jnp.arange(b)[:, None], sel].set(1 + jnp.arange(n))
    par = jnp.take_along_axis(tree.parent, sel, 1)
    par_block = jnp.where(par < 0, 0, jnp.take_along_axis(pos_of, jnp.maximum(par, 0), 1))
    ok = rules.token_accepted(spec.acceptance, spec.relax_bins, sel_bins,
                              jnp.take_along_axis(greedy, par_block, 1))  # [B, n]
    path_ok = jnp.all(~anc | ok[:, None, :], -1)  # every ancestor (and itself) accepted
    acc_depth = jnp.where(path_ok, sel_depth, 0)
    best = jnp.argmax(acc_depth, 1)  # first (highest-scoring) of the deepest
    n_acc = jnp.max(acc_depth, 1)
    best_anc = jnp.take_along_axis(anc, best[:, None, None], 1)[:, 0]  # [B, n]
    # Path block positions, by depth 1..d.
    at_depth = best_anc[:, None, :] & (sel_depth[:, None, :] == jnp.arange(1, d + 1)[None, :, None])  # [B, d, n]
    path = 1 + jnp.argmax(at_depth, -1)  # [B, d]
    path = jnp.where(jnp.arange(d)[None] < n_acc[:, None], path, 0)
    best_block = jnp.where(n_acc > 0, 1 + best, 0)
    bonus = jnp.take_along_axis(greedy, best_block[:, None], 1)[:, 0] + cfg.first_action_id
    path_tokens = jnp.take_along_axis(block, path, 1)
    tokens = jnp.concatenate([path_tokens, jnp.zeros((b, 1), jnp.int32)], 1)
    tokens = jnp.where(jnp.arange(d + 1)[None] == n_acc[:, None], bonus[:, None], tokens)
    src = jnp.concatenate([jnp.zeros((b, 1), jnp.int32), path], 1)  # root, then the path
    kept_hidden = jnp.take_along_axis(hidden, src[..., None], 1)
    return Verified(n_accepted=n_acc, path=path, tokens=tokens, hidden=kept_hidden,
                    cache=t.commit(cache, blk, src, 1 + n_acc))


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class DecodeState:
    """Where a row stands in decoding one action: the target cache holds everything before
    `root` (the last emitted token, not yet fed to the target); the drafter's cache holds the
    same committed tokens and `feat` is its predicted feature at the root's position."""
    cache: object  # the target's cache (its own pytree)
    dcache: vla.KVCache
    root: jnp.ndarray  # [B] token id
    feat: jnp.ndarray  # [B, D]
    out: jnp.ndarray  # [B, 7 + slack] emitted token ids (valid: j < n_out)
    n_out: jnp.ndarray  # [B] tokens emitted so far
    stats: dict  # per-row float counters


def start(tparams, dparams, model: target_model.Model, logits, hidden, prompt_x, cache, obs: vla.Observation,
          first: jnp.ndarray | None = None, slack: int = ACTION_DIM) -> DecodeState:
    """The state after a prefill (its last logits, prompt hidden states, embeddings and
    cache): the first token is the target's greedy choice (or `first` [B], an accepted
    draft), the drafter reads the prompt. One target pass and one drafter pass so far."""
    t = target_model.as_target(model)
    cfg = t.cfg
    b = logits.shape[0]
    root = target_model.greedy_ids(cfg, logits) if first is None else first
    feat, dcache = drafter.prompt_pass(dparams, cfg, prompt_x, hidden, vla.prompt_key_mask(cfg, obs.instruction),
                                       t.embed_tokens(tparams, root))
    out = jnp.zeros((b, ACTION_DIM + slack), jnp.int32).at[:, 0].set(root)
    stats = {"target_passes": jnp.ones((b,), jnp.float32), "drafter_passes": jnp.ones((b,), jnp.float32),
             "rounds": jnp.zeros((b,), jnp.float32)}
    return DecodeState(cache=cache, dcache=dcache, root=root, feat=feat, out=out, n_out=jnp.ones((b,), jnp.int32),
                       stats=stats)


def advance(tparams, dparams, model: target_model.Model, s: DecodeState, v: Verified) -> DecodeState:
    """Emits a verified path and its bonus token, and feeds the committed tokens to the
    drafter: entries (embedding of the next token, target hidden) for root + path, the last
    valid one (reading the bonus token) predicting the feature of the next root. Rows
    holding all 7 tokens are left unchanged; stats are not touched."""
    t = target_model.as_target(model)
    cfg = t.cfg
    b, n = v.tokens.shape  # n = longest path + 1
    active = s.n_out < ACTION_DIM
    j = jnp.arange(n)[None]
    dst = jnp.where(j <= v.n_accepted[:, None], s.n_out[:, None] + j, s.out.shape[1])  # out of range: dropped
    out = s.out.at[jnp.arange(b)[:, None], dst].set(v.tokens, mode="drop")
    n_out = jnp.minimum(s.n_out + 1 + v.n_accepted, ACTION_DIM)
    dcache = s.dcache
    slots = jnp.arange(cfg.cache_slots)
    rel = slots[None] - dcache.length[:, None]
    causal = (rel[:, None, :] >= 0) & (rel[:, None, :] <= j[..., None])  # [B, n, S]
    mask = (dcache.key_mask & (rel < 0))[:, None, :] | causal
    feats, dc = drafter.cached_pass(dparams, cfg, dcache, t.embed_tokens(tparams, v.tokens), v.hidden,
                             dcache.length[:, None] + j, dcache.length, mask)
    new_len = dcache.length + 1 + v.n_accepted
    dc = dc.replace(key_mask=dcache.key_mask | ((rel >= 0) & (slots[None] < new_len[:, None])), length=new_len)
    feat = jnp.take_along_axis(feats, v.n_accepted[:, None, None], 1)[:, 0]
    root = jnp.take_along_axis(v.tokens, v.n_accepted[:, None], 1)[:, 0]
    new = DecodeState(cache=v.cache, dcache=dc, root=root, feat=feat, out=out, n_out=n_out, stats=s.stats)
    return select_state(t, active, new, s)


def select_state(model: target_model.Model, mask: jnp.ndarray, new: DecodeState, old: DecodeState) -> DecodeState:
    """Per row: `new` where mask [B] holds, else `old` (the target's cache selected by the
    target, the drafter's by `vla.select_cache`: neither copies a whole cache)."""
    t = target_model.as_target(model)
    rows = lambda n, o: target_model.select_rows(mask, n, o)  # noqa: E731
    return DecodeState(cache=t.select_cache(mask, new.cache, old.cache),
                       dcache=vla.select_cache(mask, new.dcache, old.dcache), root=rows(new.root, old.root),
                       feat=rows(new.feat, old.feat), out=rows(new.out, old.out), n_out=rows(new.n_out, old.n_out),
                       stats=rows(new.stats, old.stats))


def round_step(tparams, dparams, model: target_model.Model, spec: SpecConfig, s: DecodeState) -> DecodeState:
    """One draft-verify round for every row (rows already holding 7 tokens are unchanged)."""
    t = target_model.as_target(model)
    active = (s.n_out < ACTION_DIM).astype(jnp.float32)
    tree = draft_tree(dparams, tparams, t, spec, s.dcache, s.feat)
    v = verify(tparams, t, spec, s.cache, s.root, tree, select_nodes(tree, spec.total_tokens))
    s = advance(tparams, dparams, t, s, v)
    stats = {**s.stats, "target_passes": s.stats["target_passes"] + active,
             "drafter_passes": s.stats["drafter_passes"] + spec.depth * active,
             "rounds": s.stats["rounds"] + active}
    return dataclasses.replace(s, stats=stats)


def rounds(tparams, dparams, model: target_model.Model, spec: SpecConfig, s: DecodeState) -> DecodeState:
    """Draft-verify rounds until every row holds 7 tokens (a `lax.while_loop`)."""
    t = target_model.as_target(model)
    return jax.lax.while_loop(lambda s: jnp.any(s.n_out < ACTION_DIM),
                              lambda s: round_step(tparams, dparams, t, spec, s), s)


def spec_decode(tparams, dparams, model: target_model.Model, spec: SpecConfig, obs: vla.Observation):
    """Speculative decoding of one action per row. Returns action token ids [B, 7] and
    per-row stats: target_passes, drafter_passes, tokens (= 7), rounds."""
    t = target_model.as_target(model)
    cfg = t.cfg
    spec.check_fits(cfg)
    logits, hidden, prompt_x, cache = t.prefill(tparams, obs)
    s = rounds(tparams, dparams, t, spec, start(tparams, dparams, t, logits, hidden, prompt_x, cache, obs,
                                                  slack=spec.depth + 1))
    b = logits.shape[0]
    return s.out[:, :ACTION_DIM], dict(s.stats, tokens=jnp.full((b,), ACTION_DIM, jnp.float32))


def decode_action(params, model: target_model.Model, obs: vla.Observation,
                  spec: SpecConfig | None = None) -> tuple[jnp.ndarray, dict[str, jnp.ndarray]]:
    """Greedy decoding of one action per observation row, in one jitted call: the public
    decode entry (docs/decode_api.md).

    spec None: autoregressive decoding (`target_model.ar_decode`); params are the target's parameters.
    spec a `SpecConfig`: drafter speculative decoding (`spec_decode`);
    params = {"target": target params, "drafter": drafter params}. With strict acceptance
    (the default) its tokens equal AR's.
    The observation is checked first (`vla.check_observation`, outside jit). Returns action
    token ids [B, 7] int32 in [cfg.first_action_id, cfg.vocab_size) (bin = id -
    first_action_id; `ActionTokenizer.to_actions` maps ids to actions) and per-row statistics,
    each [B] float32: target_passes, tokens (= 7), invalid, and for speculative decoding also
    drafter_passes and rounds. Under an outer jit the value checks cannot raise: a row whose
    proprio is not finite or whose instruction ids are out of range gets tokens
    `tokenizer.INVALID_ID` (the zero action) and invalid = 1 (`vla.mark_invalid`), the other
    rows are unchanged. model: the target's `vla.VLAConfig`, or any `target_model.TargetModel`.
    Compiles once per (model, spec, batch shape), with `xla_options.DEVICE_LOOPS` where it is
    called at top level: a call from a host loop runs its token loop, draft rounds and branches
    as device-side graph nodes on a GPU instead of returning to the host at each iteration
    (docs/scale.md measures what that saves a 7B target called once per control step). Under
    a caller's own jit it becomes part of the caller's program, compiled as the caller asks."""
    t = target_model.as_target(model)
    vla.check_observation(t.cfg, obs)
    if spec is not None:
        spec.check_fits(t.cfg)
    try:
        return _decode_action_jit(params, obs, t, spec)
    except ValueError as e:  # called under the caller's own trace (jit, grad): its program, its options
        if "top-level" not in str(e):
            raise
        return _decode_action_nested(params, obs, t, spec)


def _decode_action(params, obs: vla.Observation, model: target_model.Model, spec):
    t = target_model.as_target(model)
    if spec is None:
        tokens, stats = target_model.ar_action(params, t, obs)
    else:
        tokens, stats = spec_decode(params["target"], params["drafter"], t, spec, obs)
    return vla.mark_invalid(t.cfg, obs, tokens, stats)


_decode_action_jit = jax.jit(_decode_action, static_argnums=(2, 3), compiler_options=xla_options.DEVICE_LOOPS)
# JAX accepts compiler options on a top-level jit only; inside a caller's jit the step is inlined.
_decode_action_nested = jax.jit(_decode_action, static_argnums=(2, 3))
