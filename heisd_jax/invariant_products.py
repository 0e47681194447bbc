"""Batch-invariant numerics: every row's sums in one fixed order, whatever the batch size.

Why: a greedy decoder gives one state the same actions alone and in a batch of 256 only if
every operation computes that state's rows the same way in both. XLA does not: it picks a
GEMM kernel (tile shapes, split-K, cuBLAS or Triton) per shape, and each kernel sums a dot
product's terms in its own order. In float32 that moves a logit by ~1e-7 and a greedy token
flips only on an exact tie; in bfloat16 every product's result is rounded to 8 bits, one
rounding that goes the other way is a 0.4% change of that value, and it propagates: the
target's action at batch 1 and at batch 256 differs on a third of states (docs/target.md).

`batch_invariant(fn)` evaluates fn with:
  - every floating `dot_general` (matrix products, attention's einsums) computed on bfloat16
    operands with float32 accumulation by one Pallas kernel with fixed tiles (`Tiles`): a
    grid over the batch dimensions and over output tiles, each tile summing its K dimension in
    fixed blocks in a fixed order, so an output element gets the same sequence of tensor-core
    operations in any batch, with any number of rows beside it. The kernel reads the operands
    where they lie (strided: attention's einsums need no transposes); rows, columns and K past
    an operand's end read as zeros (a zero term leaves a sum unchanged). The result is cast to
    the product's dtype, as XLA's products do.
  - the patchify convolution (non-overlapping patches: kernel = stride, no padding) as the
    same product over the image's patches.
  - every floating `reduce_sum` (softmax denominators, RMSNorm's mean square) as a pairwise
    tree of elementwise float32 additions over the reduced axes (zero-padded to a power of
    two), whose order XLA keeps whatever the batch; a large sum on a GPU by a Pallas kernel
    that adds the same tree (`tree_sum_kernel`), where XLA's fusion of it reads uncoalesced.
This is the approach of batch-invariant kernels for LLM inference (Thinking Machines, "Defeating
Nondeterminism in LLM Inference", 2025), applied by rewriting the model's program
(`jaxpr_rewrite`), so the model needs no change. The model does two things itself under
`matmul_precision="bf16_invariant"` (`heisd_jax.vla`): the vision tower's softmax in float32,
and a pass of several tokens attending at AR's cache slots, which makes strict speculative
decoding token-identical to AR. On an H200 that gives batch 1 the tokens of batch 256 on
every state measured, with XLA's excess precision on or off (docs/target.md).

On a GPU the products run the Pallas kernel (Triton). Elsewhere they run XLA's product on the
same bfloat16 operands with float32 accumulation, which a CPU does not promise to sum alike at
every shape (on 2 cores: the same tokens on 58 of 60 states), or, with `interpret=True`, the
kernel through Pallas' interpreter (tests; slow).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from heisd_jax import jaxpr_rewrite


@dataclasses.dataclass(frozen=True)
class Tiles:
    """The kernel's one configuration: output tiles of m x n, K summed in blocks of k, on
    `warps` warps with `stages` pipelined loads. Every product of a program uses the same one,
    which is what makes it batch-invariant; which one is fastest is a device's question
    (`experiments/studies/invariant_tiles.py` times them)."""
    m: int = 64
    n: int = 64
    k: int = 32
    warps: int = 4
    stages: int = 3

    def __post_init__(self):
        for name in ("m", "n", "k"):
            v = getattr(self, name)
            if v < 16 or v & (v - 1):
                raise ValueError(f"tile {name}={v}: must be a power of two >= 16 (a tensor-core tile)")
        if self.warps not in (1, 2, 4, 8, 16):
            raise ValueError(f"warps={self.warps}: valid are 1, 2, 4, 8, 16")
        if self.stages < 1:
            raise ValueError(f"stages={self.stages}: must be >= 1")

    @classmethod
    def parse(cls, text: str) -> "Tiles":
        """'MxNxK' or 'MxNxKxWARPS' or 'MxNxKxWARPSxSTAGES', e.g. '64x64x32x4'."""
        try:
            return cls(*(int(v) for v in text.lower().split("x")))
        except (TypeError, ValueError) as e:
            raise ValueError(f"tiles {text!r}: expected MxNxK[xWARPS[xSTAGES]] of powers of two, e.g. 64x64x32x4 "
                             f"({e})") from None


@contextlib.contextmanager
def _pushed(stack: list, value):
    """`value` on top of a setting's stack (read at trace time) while inside."""
    stack.append(value)
    try:
        yield
    finally:
        stack.pop()


_tiles = [Tiles()]


def tile_shape(tiles: Tiles):
    """Products traced inside use `tiles` (a function jitted before keeps what it was traced with)."""
    return _pushed(_tiles, tiles)


SUMS = ("pairwise", "kernel", "xla")
_sums = ["pairwise"]


def sum_kind(kind: str):
    """Sums traced inside are `kind`: "pairwise" (the default: one tree, one order by
    construction; `pairwise_sum`, or for a sum over more than `_LARGE_SUM` values on a GPU
    `tree_sum_kernel`, which adds the same tree bit for bit), "kernel" (`tree_sum_kernel` at
    every size; on a GPU or interpreted, elsewhere "pairwise") or "xla" (XLA's own float32
    reduction, whose order its emitter picks; batch-invariant only as far as measured). The
    last two are for the studies that measure them."""
    if kind not in SUMS:
        raise ValueError(f"sum kind {kind!r}: valid are {', '.join(SUMS)}")
    return _pushed(_sums, kind)


def _round_up(n: int, m: int) -> int:
    return -(-n // m) * m


def _kernels(interpret: bool) -> bool:
    """Whether the Pallas kernels run: on a GPU, or anywhere through the interpreter."""
    return interpret or jax.default_backend() == "gpu"


@dataclasses.dataclass(frozen=True)
class _Operand:
    """Where an operand's dimensions are, after merging its free and contracting ones: the
    batch axes (in the product's batch order), the free axis and the contracting axis."""
    batch: tuple[int, ...]
    free: int
    contract: int


def _merged(x: jnp.ndarray, batch, free, contract):
    """x reshaped (no copy) so its free dimensions are one axis and its contracting ones
    another, where each group is adjacent and in order; else transposed to [batch, free,
    contract] first (a copy). An empty group becomes a unit axis."""
    def adjacent(group):
        return list(group) == list(range(group[0], group[0] + len(group))) if group else True
    if not (adjacent(free) and adjacent(contract)):
        x = jnp.transpose(x, (*batch, *free, *contract))
        nb = len(batch)
        batch, free, contract = tuple(range(nb)), tuple(range(nb, nb + len(free))), \
            tuple(range(nb + len(free), x.ndim))
    # Each group collapses to the position of its first dimension (or, empty, a new last axis).
    groups = [(d,) for d in batch] + [tuple(free) or None, tuple(contract) or None]
    placed = sorted((g[0], i, g) for i, g in enumerate(groups) if g)
    shape, where = [], {}
    for _, i, g in placed:
        where[i] = len(shape)
        shape.append(int(np.prod([x.shape[d] for d in g])))
    for i, g in enumerate(groups):
        if not g:
            where[i] = len(shape)
            shape.append(1)
    nb = len(batch)
    return x.reshape(shape), _Operand(tuple(where[i] for i in range(nb)), where[nb], where[nb + 1])


def _product_kernel(x_ref, y_ref, o_ref, *, xs: _Operand, ys: _Operand, batch_shape, m, n, k, tiles: Tiles):
    """One [tiles.m, tiles.n] tile of one batch element's product: its K blocks in order,
    float32 accumulation; rows, columns and K past the operands' ends read as zeros."""
    bm, bn, bk = tiles.m, tiles.n, tiles.k
    pid_b, pid_m, pid_n = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    flat, idx = pid_b, []
    for size in reversed(batch_shape):
        idx.append(flat % size)
        flat = flat // size
    idx = idx[::-1]
    rows = pid_m * bm + jnp.arange(bm)
    cols = pid_n * bn + jnp.arange(bn)

    def tile(ref, spec: _Operand, free_slice, k_slice, free_ok, k_ok):
        """The [free, tiles.k] block of ref (its batch element's), zeros outside it."""
        index = [None] * len(ref.shape)
        for axis, i in zip(spec.batch, idx):
            index[axis] = i
        index[spec.free], index[spec.contract] = free_slice, k_slice
        if spec.free < spec.contract:
            return plgpu.load(ref.at[tuple(index)], mask=free_ok[:, None] & k_ok[None, :], other=0)
        return plgpu.load(ref.at[tuple(index)], mask=k_ok[:, None] & free_ok[None, :], other=0).T

    def body(i, acc):
        ks = i * bk + jnp.arange(bk)
        k_slice = pl.ds(i * bk, bk)
        a = tile(x_ref, xs, pl.ds(pid_m * bm, bm), k_slice, rows < m, ks < k)
        b = tile(y_ref, ys, pl.ds(pid_n * bn, bn), k_slice, cols < n, ks < k)
        return acc + jnp.dot(a.astype(jnp.bfloat16), b.T.astype(jnp.bfloat16), preferred_element_type=jnp.float32)

    acc = jax.lax.fori_loop(0, _round_up(k, bk) // bk, body, jnp.zeros((bm, bn), jnp.float32))
    out = o_ref.at[pid_b, pl.ds(pid_m * bm, bm), pl.ds(pid_n * bn, bn)]
    plgpu.store(out, acc.astype(o_ref.dtype), mask=(rows < m)[:, None] & (cols < n)[None, :])


def _whole_tiles(x: jnp.ndarray, spec: _Operand, free_block: int, k_block: int) -> jnp.ndarray:
    """x zero-padded to whole tiles along its free and contracting axes: for the interpreter,
    which clamps a slice that runs past an array's end where the GPU's masked loads read nothing."""
    pad = [(0, 0)] * x.ndim
    for axis, block in ((spec.free, free_block), (spec.contract, k_block)):
        pad[axis] = (0, _round_up(x.shape[axis], block) - x.shape[axis])
    return jnp.pad(x, pad)


def dot_general(lhs, rhs, dimension_numbers, preferred_element_type=None, interpret: bool = False):
    """`jax.lax.dot_general` on bfloat16 operands with float32 accumulation, batch-invariant:
    on a GPU (or when `interpret`), one Pallas program per output tile of each batch element,
    reading the operands where they lie (strided: no transposes for the attention's einsums);
    elsewhere XLA's product of the same operands."""
    (lc, rc), (lb, rb) = dimension_numbers
    out_dtype = jnp.dtype(preferred_element_type or jnp.result_type(lhs, rhs))
    if not _kernels(interpret):
        out = jax.lax.dot_general(lhs.astype(jnp.bfloat16), rhs.astype(jnp.bfloat16), dimension_numbers,
                                  preferred_element_type=jnp.float32)
        return out.astype(out_dtype)
    lf = tuple(d for d in range(lhs.ndim) if d not in lc and d not in lb)
    rf = tuple(d for d in range(rhs.ndim) if d not in rc and d not in rb)
    batch_shape = tuple(lhs.shape[d] for d in lb)
    out_shape = (*batch_shape, *(lhs.shape[d] for d in lf), *(rhs.shape[d] for d in rf))
    m, n = int(np.prod([lhs.shape[d] for d in lf])), int(np.prod([rhs.shape[d] for d in rf]))
    k = int(np.prod([lhs.shape[d] for d in lc]))
    x, xs = _merged(lhs, tuple(lb), lf, tuple(lc))
    y, ys = _merged(rhs, tuple(rb), rf, tuple(rc))
    tiles = _tiles[-1]
    if interpret:
        x, y = _whole_tiles(x, xs, tiles.m, tiles.k), _whole_tiles(y, ys, tiles.n, tiles.k)
    bsz = int(np.prod(batch_shape))
    mp, np_ = x.shape[xs.free], y.shape[ys.free]
    kwargs = {} if interpret else {"compiler_params": plgpu.CompilerParams(num_warps=tiles.warps,
                                                                           num_stages=tiles.stages)}
    out = pl.pallas_call(
        functools.partial(_product_kernel, xs=xs, ys=ys, batch_shape=batch_shape or (1,), m=m, n=n, k=k,
                          tiles=tiles),
        out_shape=jax.ShapeDtypeStruct((bsz, mp, np_), out_dtype),
        grid=(bsz, -(-m // tiles.m), -(-n // tiles.n)),
        interpret=interpret,
        **kwargs,
    )(x, y)
    if (mp, np_) != (m, n):
        out = out[:, :m, :n]
    return out.reshape(out_shape)


# A sum over more values than this (8 MiB of float32; a batch-16 prefill's attention is more, batch
# 1's passes less) is a large one: on a GPU `tree_sum_kernel`'s, elsewhere `pairwise_sum` adds its
# wide tree levels one kernel each. At a batch-512 prefill's attention sum on an H200 the tree in
# one fusion took 1.92 ms, its levels apart 0.38, the kernel 0.12 (XLA's own sum 0.11); at batch 16
# all took 0.03-0.04 ms (experiments/studies/invariant_tiles.py). Not tuned further.
_LARGE_SUM = 1 << 21
_FUSED_WIDTH = 32


def _rows(x: jnp.ndarray, axes) -> tuple[jnp.ndarray, int]:
    """x as [*kept dims, n]: the values each output sums (the reduced axes, flattened) last; and
    the width of their tree (n rounded up to a power of two)."""
    axes = tuple(sorted(a % x.ndim for a in axes))
    kept = [d for d in range(x.ndim) if d not in axes]
    n = int(np.prod([x.shape[d] for d in axes]))
    v = jnp.transpose(x, (*kept, *axes)).reshape(*(x.shape[d] for d in kept), n)
    return v, 1 << max(n - 1, 0).bit_length()


def pairwise_sum(x: jnp.ndarray, axes, level_kernels_above: int | None = None) -> jnp.ndarray:
    """jnp.sum(x, axes) as a pairwise tree of float32 additions (the reduced axes flattened,
    zero-padded to a power of two, halves added until one is left), in x's dtype. Each output
    element's additions are fixed by the number of values it sums alone.

    XLA fuses a whole tree into one loop in which each output strides through its own values,
    uncoalesced: at a batch-512 prefill's attention, the largest kernel of the pass. So a large
    sum (over `level_kernels_above` values in all, default `_LARGE_SUM`) materialises
    each level wider than `_FUSED_WIDTH` (an optimisation barrier), where neighbouring threads
    add neighbouring values; the narrow rest is one fusion. Where the kernels split the tree
    does not change a single addition, so every shape gets the same bits, and small sums (batch
    1) keep one kernel (`experiments/studies/invariant_tiles.py` times both ways)."""
    v, width = _rows(x, axes)
    v = jnp.pad(v.astype(jnp.float32), [(0, 0)] * (v.ndim - 1) + [(0, width - v.shape[-1])])
    split = v.size > (_LARGE_SUM if level_kernels_above is None else level_kernels_above)
    while v.shape[-1] > 1:
        half = v.shape[-1] // 2
        v = v[..., :half] + v[..., half:]
        if split and half > _FUSED_WIDTH:
            v = jax.lax.optimization_barrier(v)
    return v[..., 0].astype(x.dtype)


_SUM_BLOCK = 4096  # values one program of `tree_sum_kernel` holds: rows x the tree's width
_SUM_WIDEST = 16384  # a wider tree is `pairwise_sum`'s (one row would not fit a program's registers)


def _tree_sum_kernel(x_ref, o_ref, *, rows: int, n: int, width: int, block_rows: int):
    """One block of rows' sums: the row's values (zeros past n) halved `width` -> 1, each
    level adding value j to value j + half, as `pairwise_sum` adds them. (Not a reshape and a
    sum over the pairs: XLA, which runs the interpreter, merges consecutive reductions into one
    and reorders it.)"""
    pid = pl.program_id(0)
    r = pid * block_rows + jnp.arange(block_rows)
    c = jnp.arange(width)
    v = plgpu.load(x_ref.at[pl.ds(pid * block_rows, block_rows), pl.ds(0, width)],
                   mask=(r < rows)[:, None] & (c < n)[None, :], other=0).astype(jnp.float32)
    while v.shape[1] > 1:
        lo, hi = jnp.split(v, 2, axis=1)  # lax.split: Triton's reshape, transpose and split
        v = lo + hi
    plgpu.store(o_ref.at[pl.ds(pid * block_rows, block_rows)], v.reshape(block_rows).astype(o_ref.dtype),
                mask=r < rows)


def tree_sum_kernel(x: jnp.ndarray, axes, interpret: bool = False) -> jnp.ndarray:
    """`pairwise_sum(x, axes)`, bit for bit, as one Pallas kernel: each program loads a block of
    rows whole (neighbouring values at neighbouring addresses) and adds each row's tree in
    registers, where XLA's fusion of the tree reads every row strided. Rows wider than
    `_SUM_WIDEST` values fall back to `pairwise_sum`."""
    v, width = _rows(x, axes)
    kept_shape, n = v.shape[:-1], v.shape[-1]
    rows = int(np.prod(kept_shape))
    if width > _SUM_WIDEST or rows == 0:
        return pairwise_sum(x, axes)
    v = v.reshape(rows, n)
    block_rows = max(1, _SUM_BLOCK // width)
    if interpret:  # the interpreter clamps a slice past the end where the GPU's masked loads read nothing
        v = jnp.pad(v, ((0, _round_up(rows, block_rows) - rows), (0, width - n)))
    out = pl.pallas_call(
        functools.partial(_tree_sum_kernel, rows=rows, n=n, width=width, block_rows=block_rows),
        out_shape=jax.ShapeDtypeStruct((_round_up(rows, block_rows) if interpret else rows,), x.dtype),
        grid=(-(-rows // block_rows),),
        interpret=interpret,
        **({} if interpret else {"compiler_params": plgpu.CompilerParams(num_warps=4, num_stages=1)}),
    )(v)
    return out[:rows].reshape(kept_shape)


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)


def _product_rule(interpret):
    def rule(invals, *, dimension_numbers, preferred_element_type=None, **params):
        lhs, rhs = invals
        if not (_is_float(lhs) and _is_float(rhs)):
            return jax.lax.dot_general_p.bind(lhs, rhs, dimension_numbers=dimension_numbers,
                                              preferred_element_type=preferred_element_type, **params)
        return dot_general(lhs, rhs, dimension_numbers, preferred_element_type, interpret)

    return rule


def _sum_rule(interpret):
    def rule(invals, *, axes, **params):
        (x,) = invals
        if not _is_float(x) or not axes:
            return jax.lax.reduce_sum_p.bind(x, axes=axes, **params)
        if _sums[-1] == "xla":
            return jnp.sum(x.astype(jnp.float32), axes).astype(x.dtype)
        large_on_gpu = x.size > _LARGE_SUM and jax.default_backend() == "gpu"
        if _sums[-1] == "kernel" and _kernels(interpret) or _sums[-1] == "pairwise" and large_on_gpu:
            return tree_sum_kernel(x, axes, interpret)
        return pairwise_sum(x, axes)

    return rule


def _patchify_rule(interpret):
    """A convolution whose kernel tiles the input (stride = kernel size, no padding or
    dilation, one group, NHWC / HWIO / NHWC) as a product over the patches."""

    def rule(invals, *, window_strides, padding, lhs_dilation, rhs_dilation, dimension_numbers,
             feature_group_count, batch_group_count, preferred_element_type=None, **params):
        x, w = invals
        kh, kw, cin, cout = w.shape
        plain = (tuple(window_strides) == (kh, kw) and all(tuple(p) == (0, 0) for p in padding)
                 and set(lhs_dilation) == {1} and set(rhs_dilation) == {1}
                 and feature_group_count == 1 and batch_group_count == 1
                 and tuple(dimension_numbers.lhs_spec) == (0, 3, 1, 2)
                 and tuple(dimension_numbers.rhs_spec) == (3, 2, 0, 1)
                 and tuple(dimension_numbers.out_spec) == (0, 3, 1, 2)
                 and x.shape[1] % kh == 0 and x.shape[2] % kw == 0)
        if not plain:
            raise NotImplementedError(
                "batch-invariant numerics compute a convolution only as a patchify (NHWC input, HWIO "
                f"kernel, stride = kernel size, no padding); got strides {window_strides}, padding {padding}, "
                f"kernel {w.shape}")
        b, h, wd, _ = x.shape
        patches = x.reshape(b, h // kh, kh, wd // kw, kw, cin).transpose(0, 1, 3, 2, 4, 5)
        patches = patches.reshape(1, b * (h // kh) * (wd // kw), kh * kw * cin)
        out_dtype = jnp.dtype(preferred_element_type or jnp.result_type(x, w))
        out = dot_general(patches, w.reshape(1, kh * kw * cin, cout), (((2,), (1,)), ((0,), (0,))),
                          out_dtype, interpret)
        return out.reshape(b, h // kh, wd // kw, cout)

    return rule


def batch_invariant(fn, interpret: bool = False):
    """fn with batch-invariant products, patchify convolutions and sums (the module's
    docstring); `interpret`: the products by the Pallas kernel's interpreter on any backend."""
    rules = {"dot_general": _product_rule(interpret), "conv_general_dilated": _patchify_rule(interpret),
             "reduce_sum": _sum_rule(interpret)}
    return jaxpr_rewrite.with_rules(fn, rules)
