"""`invariant_products`: the fixed-tile product kernel computes dot_general for every operand
layout the model uses (natively on a GPU, by Pallas' interpreter elsewhere), a row's result
does not depend on the rows beside it, sums are pairwise trees, the patchify convolution is
the same product, and the model's bf16_invariant numerics give one state the same logits
alone and in a batch."""

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax import invariant_products as ip
from heisd_jax import vla
from tiny_models import CFG, obs

INTERPRET = jax.default_backend() != "gpu"  # the kernel itself on a GPU, its interpreter elsewhere


def _random(shape, seed, dtype=jnp.bfloat16):
    return jax.random.normal(jax.random.key(seed), shape, jnp.float32).astype(dtype)


@pytest.mark.parametrize("spec,a,b", [
    ("btk,kn->btn", (3, 70, 100), (100, 90)),  # a Dense layer: rows past a tile, K past a block
    ("btk,kn->btn", (1, 1, 256), (256, 96)),  # one token's pass: a row far short of a tile
    ("bthd,bshd->bhts", (2, 5, 4, 16), (2, 70, 4, 16)),  # attention scores, batch axes between the others
    ("bhts,bshd->bthd", (2, 4, 5, 70), (2, 70, 4, 16)),  # attention weights times values
    ("bshd,hdk->bsk", (2, 7, 4, 16), (4, 16, 33)),  # two contracting axes (an attention's output projection)
    ("km,kn->mn", (40, 70), (40, 90)),  # contracting axis first: read transposed
])
def test_the_kernel_computes_dot_general_for_every_layout(spec, a, b):
    x, y = _random(a, 0), _random(b, 1)
    got = ip.batch_invariant(lambda x, y: jnp.einsum(spec, x, y, preferred_element_type=jnp.float32),
                             interpret=INTERPRET)(x, y)
    want = np.einsum(spec, np.asarray(x, np.float64), np.asarray(y, np.float64))
    assert got.shape == want.shape and got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-5 * np.abs(want).max())


def test_float32_operands_are_rounded_to_bfloat16_and_the_result_keeps_their_dtype():
    x, w = _random((4, 64), 2, jnp.float32), _random((64, 32), 3, jnp.float32)
    got = ip.batch_invariant(lambda x, w: x @ w, interpret=INTERPRET)(x, w)
    assert got.dtype == jnp.float32
    want = np.asarray(x.astype(jnp.bfloat16), np.float64) @ np.asarray(w.astype(jnp.bfloat16), np.float64)
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-5 * np.abs(want).max())


def test_a_row_gets_the_same_bits_alone_and_in_a_batch():
    x, w = _random((6, 70, 100), 4), _random((100, 90), 5)
    dense = jax.jit(ip.batch_invariant(lambda x: x @ w, interpret=INTERPRET))
    whole = np.asarray(dense(x), np.float32)
    np.testing.assert_array_equal(whole[:1], np.asarray(dense(x[:1]), np.float32))  # one batch row
    np.testing.assert_array_equal(whole[:, :1], np.asarray(dense(x[:, :1]), np.float32))  # one token
    q, k = _random((5, 3, 4, 16), 6), _random((5, 40, 4, 16), 7)
    scores = jax.jit(ip.batch_invariant(lambda q, k: jnp.einsum("bthd,bshd->bhts", q, k), interpret=INTERPRET))
    np.testing.assert_array_equal(np.asarray(scores(q, k)[:1], np.float32), np.asarray(scores(q[:1], k[:1]), np.float32))


def test_sums_are_pairwise_trees_of_the_values():
    x = _random((3, 300, 5), 8, jnp.float32)
    got = ip.pairwise_sum(x, (1, 2))
    np.testing.assert_allclose(np.asarray(got), np.asarray(x, np.float64).sum((1, 2)), rtol=1e-5)
    assert ip.pairwise_sum(x, (1,)).shape == (3, 5) and ip.pairwise_sum(x.astype(jnp.bfloat16), (1,)).dtype == jnp.bfloat16
    # the tree itself, bit for bit: zero-padded to a power of two, the halves added until one is
    # left; a sum too large for one fused kernel (its wide levels one kernel each) adds the same
    def tree(v):
        v = np.pad(v, ((0, 0), (0, (1 << (v.shape[1] - 1).bit_length()) - v.shape[1])))
        while v.shape[1] > 1:
            v = v[:, :v.shape[1] // 2] + v[:, v.shape[1] // 2:]
        return v[:, 0]

    np.testing.assert_array_equal(np.asarray(got), tree(np.asarray(x).reshape(3, 1500)))
    large = np.asarray(_random((7000, 300), 11, jnp.float32))
    assert large.size > ip._LARGE_SUM
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda v: ip.pairwise_sum(v, (1,)))(large)), tree(large))
    # the rewritten softmax sums with the tree: a row alone and in a batch agree bit for bit
    soft = jax.jit(ip.batch_invariant(lambda v: jax.nn.softmax(v, -1)))
    np.testing.assert_array_equal(np.asarray(soft(x[:, :, 0])[:1]), np.asarray(soft(x[:1, :, 0])))


@pytest.mark.parametrize("shape,axes", [((40, 3, 149), (2,)), ((3, 300, 5), (1, 2)), ((4, 6, 33), (0, 2)),
                                        ((5, 1), (1,)), ((2, 20000), (1,))])
def test_the_sum_kernel_adds_the_pairwise_tree_bit_for_bit(shape, axes):
    x = _random(shape, 13, jnp.float32) * 100
    want = np.asarray(ip.pairwise_sum(x, axes))
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda v: ip.tree_sum_kernel(v, axes, interpret=True))(x)), want)
    # and as the rewrite's sums, in a softmax
    with ip.sum_kind("kernel"):
        soft = jax.jit(ip.batch_invariant(lambda v: jax.nn.softmax(v, -1), interpret=True))
        got = np.asarray(soft(x.reshape(-1, shape[-1])))
    np.testing.assert_array_equal(got, np.asarray(jax.jit(ip.batch_invariant(lambda v: jax.nn.softmax(v, -1)))(
        x.reshape(-1, shape[-1]))))


def test_the_patchify_convolution_is_the_product_over_patches_and_others_are_refused():
    img = jax.random.uniform(jax.random.key(9), (2, 16, 32, 3), jnp.float32, -1, 1)
    conv = nn.Conv(24, (8, 8), strides=8, dtype=jnp.bfloat16)
    p = conv.init(jax.random.key(10), img)
    got = ip.batch_invariant(conv.apply, interpret=INTERPRET)(p, img)
    want = conv.apply(p, img)
    assert got.shape == want.shape == (2, 2, 4, 24)
    np.testing.assert_allclose(np.asarray(got, np.float32), np.asarray(want, np.float32), atol=2e-2)
    overlapping = nn.Conv(24, (8, 8), strides=4, dtype=jnp.bfloat16)
    with pytest.raises(NotImplementedError, match="only as a patchify"):
        ip.batch_invariant(overlapping.apply)(overlapping.init(jax.random.key(10), img), img)


def test_the_models_bf16_invariant_numerics_give_a_state_the_same_logits_alone_and_in_a_batch():
    base = dataclasses.replace(CFG, dtype="bfloat16")
    cfg = dataclasses.replace(base, matmul_precision="bf16_invariant")
    params = jax.tree.map(lambda p: p.astype(jnp.bfloat16), vla.init_params(CFG, jax.random.PRNGKey(2)))
    o = obs(batch=4)
    prefill = jax.jit(lambda p, o, c: vla.prefill(p, c, o)[0], static_argnums=2)
    whole, alone = prefill(params, o, cfg), prefill(params, jax.tree.map(lambda x: x[:1], o), cfg)
    np.testing.assert_array_equal(np.asarray(whole[:1]), np.asarray(alone))
    # the same function as XLA's bf16 numerics, up to bf16 roundings
    np.testing.assert_allclose(np.asarray(whole), np.asarray(prefill(params, o, base)), atol=0.05)


def test_a_tree_pass_gives_each_token_the_logits_of_ars_single_token_passes_bit_for_bit():
    """Under bf16_invariant a pass of several tokens against the cache, or after the prompt in the
    prefill, attends at AR's slots (`vla.ancestor_slots`), so strict verification is
    token-identical to AR in bf16: the tree [a0 -> a1 -> a2, a0 -> x] in one pass (and fused
    into the prefill, as retrieval verifies) against AR committing a0, a1 one pass at a time
    (and x after a0)."""
    cfg = dataclasses.replace(CFG, dtype="bfloat16", matmul_precision="bf16_invariant")
    params = jax.tree.map(lambda p: p.astype(jnp.bfloat16), vla.init_params(CFG, jax.random.PRNGKey(5)))
    o = obs(seed=3, batch=2)
    run = lambda f: jax.jit(ip.batch_invariant(f, interpret=INTERPRET))  # noqa: E731  the kernel, not XLA's dot
    _, _, cache = run(lambda p, o: vla.prefill(p, cfg, o))(params, o)
    ids = jnp.asarray([[40, 90, 200, 77], [41, 91, 201, 78]], jnp.int32)  # a0, a1, a2, x per row
    one = run(lambda p, c, t: vla.cached_pass(p, cfg, c, t, jnp.zeros((2, 1), jnp.int32), jnp.ones((2, 1, 1), bool)))
    keep = jax.jit(lambda c, blk: vla.commit(c, blk, jnp.zeros((2, 1), jnp.int32), jnp.ones((2,), jnp.int32)))
    ar, c = [], cache
    for j in range(3):  # a0, a1, a2 in turn
        lg, _, blk = one(params, c, ids[:, j:j + 1])
        ar.append(lg[:, 0])
        c = keep(c, blk)
        if j == 0:
            after_a0 = c
    x_after_a0 = one(params, after_a0, ids[:, 3:4])[0][:, 0]
    parent = np.array([-1, 0, 1, 0])
    intra = np.eye(4, dtype=bool)
    for i in range(4):
        j = parent[i]
        while j >= 0:
            intra[i, j], j = True, parent[j]
    depth = jnp.asarray(np.broadcast_to([0, 1, 2, 1], (2, 4)), jnp.int32)
    tree = run(lambda p, c, t, d, m: vla.cached_pass(p, cfg, c, t, d, m)[0])(
        params, cache, ids, depth, jnp.asarray(np.broadcast_to(intra, (2, 4, 4))))
    fused = run(lambda p, o, t, d, m: vla.prefill_with_block(p, cfg, o, t, d, m)[3])(  # retrieval's fused verification
        params, o, ids, depth, jnp.asarray(np.broadcast_to(intra, (2, 4, 4))))
    for i, want in enumerate([*ar, x_after_a0]):
        np.testing.assert_array_equal(np.asarray(tree[:, i]), np.asarray(want), err_msg=f"tree token {i}")
        np.testing.assert_array_equal(np.asarray(fused[:, i]), np.asarray(want), err_msg=f"prefill block token {i}")


def test_another_tile_shape_computes_the_same_product_and_bad_ones_are_refused():
    x, w = _random((3, 70, 100), 11), _random((100, 90), 12)
    with ip.tile_shape(ip.Tiles.parse("16x32x64x2")):
        got = jax.jit(ip.batch_invariant(lambda x, w: jnp.einsum("btk,kn->btn", x, w, preferred_element_type=jnp.float32),
                                         interpret=INTERPRET))(x, w)
    want = np.einsum("btk,kn->btn", np.asarray(x, np.float64), np.asarray(w, np.float64))
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-5 * np.abs(want).max())
    assert ip.Tiles.parse("64x64x32") == ip.Tiles()
    for bad, message in (("64x48x32", "n=48: must be a power of two"), ("8x64x32", "m=8"),
                         ("64x64x32x3", "warps=3: valid are"), ("64by64", "expected MxNxK")):
        with pytest.raises(ValueError, match=message):
            ip.Tiles.parse(bad)
    with pytest.raises(ValueError, match="sum kind 'tree': valid are pairwise, kernel, xla"):
        with ip.sum_kind("tree"):
            pass


def test_large_sums_take_the_kernel_on_a_gpu_and_small_ones_the_fused_tree(monkeypatch):
    """The default sums route by size on a GPU: over `_LARGE_SUM` values, the Pallas kernel
    (which adds the same tree); below, the tree in XLA's own fusion. Elsewhere always the tree."""
    def kernels_in(v):
        return str(jax.make_jaxpr(ip.batch_invariant(lambda v: jnp.sum(v, -1), interpret=True))(v)).count("pallas_call")

    small, large = jnp.zeros((4, 300)), jnp.zeros((ip._LARGE_SUM // 256 + 1, 512))
    assert kernels_in(small) == kernels_in(large) == 0  # on this CPU
    monkeypatch.setattr(ip.jax, "default_backend", lambda: "gpu")
    assert kernels_in(small) == 0 and kernels_in(large) == 1
