"""VLA training and checkpoints on a tiny synthetic dataset."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from envs import demos, language
from heisd_jax import checkpoint, vla
from heisd_jax.harness import data, training
from heisd_jax.tokenizer import ActionTokenizer

CFG = vla.VLAConfig(image_size=16, patch_size=8, vision_layers=1, d_model=32, n_layers=2, n_heads=4, mlp_dim=64,
                    cache_slots=48)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """20 episodes whose actions depend on the proprio input (learnable)."""
    path = tmp_path_factory.mktemp("d") / "demos"
    rng = np.random.default_rng(0)
    w = demos.DatasetWriter(path, {"image_size": 16})
    n_ep, n = 20, 10
    proprio = rng.normal(size=(n_ep * n, 8)).astype(np.float32)
    action = np.tanh(proprio[:, :7] * 1.5).astype(np.float32)
    action[:, 6] = np.sign(action[:, 6])
    steps = dict(image=rng.integers(0, 255, (n_ep * n, 16, 16, 3), dtype=np.uint8), proprio=proprio, action=action,
                 ee_vel=np.zeros((n_ep * n, 3), np.float32), ee_ang_vel=np.zeros((n_ep * n, 3), np.float32),
                 ee_acc=np.zeros((n_ep * n, 3), np.float32), gripper_vel=np.zeros(n_ep * n, np.float32))
    w.add_shard(steps, [dict(task="lift_blue_cylinder", instruction="pick up the blue cylinder and hold it up",
                             start=i * n, length=n) for i in range(n_ep)])
    return w.finalize()


def test_a_few_training_steps_lower_the_loss(dataset):
    table = jax.device_put(data.load_steps(str(dataset)))
    assert table.size == 200 and table.instruction.shape == (200, CFG.text_len)
    tok = ActionTokenizer.fit(np.asarray(table.action), CFG.vocab_size)
    cfg = training.TrainConfig(steps=60, batch_size=32, lr=3e-3, warmup_steps=5)
    state = training.init_state(CFG, cfg)
    step = training.make_train_step(CFG, cfg, tok)
    ev = training.make_eval_fn(CFG, tok, 128, cfg)
    key = jax.random.PRNGKey(0)
    before, untrained = ev(state.params, table, key)
    for _ in range(cfg.steps):
        state, m = step(state, table, key)
    after, metrics = ev(state.params, table, key)
    assert int(state.step) == cfg.steps
    assert float(after) < float(before) - 0.5, (float(before), float(after))
    assert metrics["token_acc"].shape == metrics["bin_err"].shape == metrics["decisive"].shape == (7,)
    # An untrained head spreads its probability over the 256 bins: no token is decisive (> 0.5);
    # training makes some of them so (the gripper's two states first).
    assert float(np.max(untrained["decisive"])) == 0.0 and float(np.max(metrics["decisive"])) > 0.0


def test_training_continues_from_a_bf16_policy_in_float32_master_weights(dataset):
    table = jax.device_put(data.load_steps(str(dataset)))
    tok = ActionTokenizer.fit(np.asarray(table.action), CFG.vocab_size)
    cfg = training.TrainConfig(steps=2, batch_size=16, lr=3e-3, warmup_steps=1)
    stored = checkpoint.as_param_dtype(vla.init_params(CFG, jax.random.PRNGKey(7)), "bfloat16")
    state = training.continue_from(CFG, cfg, stored)
    for own, new in zip(jax.tree.leaves(state.params), jax.tree.leaves(stored)):
        assert own.dtype == jnp.float32 and new.dtype == jnp.bfloat16
        np.testing.assert_array_equal(own, new.astype(jnp.float32))  # the stored values, exactly
    # ... the very state of a random initialisation with its parameters replaced, optimizer state and step included.
    fresh = training.init_state(CFG, cfg)
    replaced = fresh.replace(params=jax.tree.map(lambda new, own: new.astype(own.dtype), stored, fresh.params))
    assert jax.tree.structure(state) == jax.tree.structure(replaced)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(replaced)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    state, _ = training.make_train_step(CFG, cfg, tok)(state, table, jax.random.PRNGKey(0))
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(state.params))  # updates stay in float32


def test_action_loss_is_the_cross_entropy_at_the_action_positions_with_or_without_padding():
    """`action_loss` (the head from the first action position on, the sequence optionally padded
    to a multiple) equals the cross-entropy read off the whole teacher-forced pass's logits, since
    no position attends to a later one."""
    params = jax.tree.map(lambda x: x * 3.0, vla.init_params(CFG, jax.random.PRNGKey(1)))
    rng = np.random.default_rng(0)
    obs = vla.Observation(image=jnp.asarray(rng.integers(0, 255, (4, *CFG.image_shape)), jnp.uint8),
                          instruction=jnp.asarray(np.r_[1, 5, 6, 2, [0] * (CFG.text_len - 4)][None].repeat(4, 0), jnp.int32),
                          proprio=jnp.asarray(rng.normal(size=(4, 8)), jnp.float32))
    tokens = jnp.asarray(CFG.first_action_id + rng.integers(0, 256, (4, 7)), jnp.int32)
    logits, _ = vla.forward(params, CFG, obs, tokens)
    p = CFG.prompt_len
    pred = vla.action_logits(CFG, logits[:, p - 1: p + 6])
    want = optax.softmax_cross_entropy(pred, training.soft_bin_targets(tokens - CFG.first_action_id, 256, 2.0)).mean()
    assert (p + 7) % 24, "the padding below must change the sequence's length"
    for multiple in (1, 24):
        loss, metrics = jax.jit(lambda q, m=multiple: training.action_loss(q, CFG, obs, tokens, 2.0, m))(params)
        np.testing.assert_allclose(float(loss), float(want), rtol=1e-5)
        np.testing.assert_array_equal(metrics["token_acc"], jnp.mean(pred.argmax(-1) == tokens - CFG.first_action_id, 0))
    with pytest.raises(ValueError, match="seq_multiple"):
        training.TrainConfig(seq_multiple=0)


def test_soft_bin_targets_are_distributions_with_the_label_as_mode():
    bins = jnp.array([[0, 17, 255]])
    hard = training.soft_bin_targets(bins, 256, 0.0)
    np.testing.assert_array_equal(np.asarray(hard), np.asarray(jax.nn.one_hot(bins, 256)))
    soft = np.asarray(training.soft_bin_targets(bins, 256, 2.0))
    np.testing.assert_allclose(soft.sum(-1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(soft.argmax(-1), np.asarray(bins))
    assert soft[0, 1, 16] == soft[0, 1, 18] > soft[0, 1, 19] > 0  # symmetric, decaying
    with pytest.raises(ValueError, match="label_sigma_bins"):
        training.TrainConfig(label_sigma_bins=-1.0)


def test_split_is_by_episode_and_disjoint(dataset):
    tr, va = data.random_episode_split(str(dataset), 0.2)
    assert len(va) == 4 and not set(tr) & set(va) and sorted(tr + va) == list(range(20))


def test_a_table_of_several_datasets_holds_their_episodes_steps_in_order(dataset, tmp_path):
    ds = demos.DemoDataset(dataset)
    table = data.load_step_table([(str(dataset), [3, 1]), (str(dataset), None)])
    order = [3, 1, *range(len(ds))]
    assert table.size == sum(ds.episodes[i]["length"] for i in order)
    for field in ("image", "proprio", "action"):
        np.testing.assert_array_equal(getattr(table, field), np.concatenate([ds.episode(i)[field] for i in order]))
    np.testing.assert_array_equal(table.instruction[0], language.to_ids(ds.episodes[3]["instruction"]))
    # Datasets of other image shapes cannot share a table: the error names both.
    other = demos.DatasetWriter(tmp_path / "small", {"image_size": 8})
    other.add_shard({f: v[:10] if f != "image" else v[:10, :8, :8] for f, v in ds.shard(0).items()},
                    [dict(ds.episodes[0], start=0, length=10)])
    with pytest.raises(ValueError, match="different shapes.*small"):
        data.load_step_table([(str(dataset), None), (str(other.finalize()), None)])


def test_task_weights_draw_each_step_in_proportion_to_its_tasks_weight(dataset, tmp_path):
    """A table loaded with task weights holds each step's weight (its episode's task's) and
    draws rows in proportion to it; one without, or whose weights are all 1, draws uniformly
    with the very indices of `jax.random.randint` (builds without weights keep their data order)."""
    ds = demos.DemoDataset(dataset)
    path = tmp_path / "two_tasks"
    w = demos.DatasetWriter(path, {"image_size": 16})
    lengths, names = [3, 5, 2, 4], ["pick_red_block", "lift_blue_cylinder"] * 2
    starts = np.cumsum([0, *lengths[:-1]])
    w.add_shard({f: v[:sum(lengths)] for f, v in ds.shard(0).items()},
                [dict(ds.episodes[0], task=t, start=int(s), length=n) for t, s, n in zip(names, starts, lengths)])
    path = str(w.finalize())
    weighted = data.load_step_table([(path, None)], task_weights={"pick_red_block": 3, "stack_red_on_green": 2})
    expected = np.repeat([3, 1, 3, 1], lengths)
    np.testing.assert_array_equal(np.diff(weighted.cumulative_weight, prepend=0), expected)
    n, key = 48_000, jax.random.PRNGKey(0)
    draw = jax.jit(data.draw_rows, static_argnums=2)
    counts = np.bincount(np.asarray(draw(jax.device_put(weighted), key, n)), minlength=len(expected))
    np.testing.assert_allclose(counts / n, expected / expected.sum(), rtol=0.1)  # ~5 sigma for a weight-1 row
    for table in (data.load_step_table([(path, None)]), data.load_step_table([(path, None)], {"lift_blue_cylinder": 1})):
        assert table.cumulative_weight is None
        np.testing.assert_array_equal(draw(jax.device_put(table), key, 64), jax.random.randint(key, (64,), 0, table.size))
    with pytest.raises(ValueError, match="positive integers"):
        data.load_step_table([(path, None)], {"pick_red_block": 0})


def test_source_weights_multiply_task_weights_and_set_each_datasets_share_of_the_draws(dataset):
    """`source_weights` scales every step of its dataset on top of its task's weight, and
    `draw_share` gives each dataset's share of the draws (what experiments.train prints)."""
    n = demos.DemoDataset(dataset).episodes[0]["length"]
    sources = [(str(dataset), [0, 1]), (str(dataset), [2])]
    table = data.load_step_table(sources, {"lift_blue_cylinder": 2}, source_weights=[1, 3])
    np.testing.assert_array_equal(np.diff(table.cumulative_weight, prepend=0), np.repeat([2, 2, 6], n))
    assert data.draw_share(table, slice(0, 2 * n)) == pytest.approx(4 / 10)
    assert data.draw_share(table, slice(2 * n, 3 * n)) == pytest.approx(6 / 10)
    draws = np.asarray(jax.jit(data.draw_rows, static_argnums=2)(jax.device_put(table), jax.random.PRNGKey(0), 20_000))
    assert np.mean(draws >= 2 * n) == pytest.approx(0.6, abs=0.02)
    uniform = data.load_step_table(sources, source_weights=[1, 1])  # all 1: the uniform draw, no weights stored
    assert uniform.cumulative_weight is None and data.draw_share(uniform, slice(0, 2 * n)) == pytest.approx(2 / 3)
    for bad in ([1], [1, 0], [1, 1.5]):
        with pytest.raises(ValueError, match="one positive integer per dataset"):
            data.load_step_table(sources, source_weights=bad)


def test_train_refuses_demo_weights_that_do_not_match_its_datasets(dataset, tmp_path):
    """A --demo_weights list of the wrong length or with a non-positive entry is refused in one
    line naming the flag, before any data is loaded or any run directory made."""
    for weights in ("1", "1,0", "1,x"):
        r = subprocess.run([sys.executable, "-m", "experiments.train", f"--demos={dataset},{dataset}",
                            f"--demo_weights={weights}", f"--out={tmp_path / 'run'}"], capture_output=True, text=True,
                           cwd=Path(__file__).resolve().parents[1], timeout=300)
        assert r.returncode != 0 and "--demo_weights: expected one positive integer per --demos dataset (2), got " \
            f"{weights}" in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "run").exists()


def test_a_longer_table_compiles_the_draw_again_not_the_update(dataset, caplog):
    """A DAgger round trains on a longer table than the round before. The update's program does
    not depend on the table's length, so the persistent cache answers it in every later round
    with the same settings; only the minibatch draw compiles again."""
    full = jax.device_put(data.load_steps(str(dataset)))
    part = jax.device_put(data.load_steps(str(dataset), list(range(12))))
    tok = ActionTokenizer.fit(np.asarray(full.action), CFG.vocab_size)
    cfg = training.TrainConfig(steps=10, batch_size=8, warmup_steps=1, image_shift=1)
    state, step = training.init_state(CFG, cfg), training.make_train_step(CFG, cfg, tok)
    key = jax.random.PRNGKey(0)
    with jax.log_compiles(True), caplog.at_level("WARNING"):
        for table in (part, full, full):
            state, _ = step(state, table, key)
    compiled = [r.getMessage().split()[1] for r in caplog.records if r.getMessage().startswith("Compiling ")]
    assert compiled.count("jit(draw)") == 2 and compiled.count("jit(update)") == 1, compiled


def test_a_round_with_other_settings_runs_the_same_update_program(dataset):
    """The learning rate, its schedule and the label width are the update's inputs: a build's
    first policy and its fine-tuning rounds share one compiled update."""
    table = jax.device_put(data.load_steps(str(dataset)))
    tok = ActionTokenizer.fit(np.asarray(table.action), CFG.vocab_size)
    first = training.TrainConfig(steps=60, batch_size=8, lr=5e-4, warmup_steps=30, label_sigma_bins=2.0)
    later = training.TrainConfig(steps=45, batch_size=8, lr=2.5e-4, warmup_steps=20, label_sigma_bins=0.6)
    state = training.init_state(CFG, first)
    steps = [training.make_train_step(CFG, c, tok) for c in (first, later)]
    batch = steps[0].draw(table, state.step, jax.random.PRNGKey(0))
    hlo = [s.update.lower(state, s.settings, batch).as_text() for s in steps]
    assert hlo[0] == hlo[1]
    # ... and the settings do reach it: the second updates differ (the first has a learning rate of 0).
    (a, _), (b, _) = (s.update(s.update(state, s.settings, batch)[0], s.settings, batch) for s in steps)
    assert any(not np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params)))


def test_the_schedule_is_optax_warmup_cosine_decay():
    peak, warmup, steps = 5e-4, 300, 6000
    want = optax.warmup_cosine_decay_schedule(0.0, peak, warmup, steps, end_value=peak * training.END_LR_FRACTION)
    got = training.lr_schedule(jnp.float32(peak), jnp.float32(warmup), jnp.float32(steps))
    counts = np.array([0, 1, 150, 299, 300, 301, 1000, 3150, 5999, 6000, 7000])
    np.testing.assert_allclose([float(got(c)) for c in counts], [float(want(c)) for c in counts], rtol=2e-5,
                               atol=1e-10)


@pytest.fixture(scope="module")
def policy_ckpt(tmp_path_factory):
    params = vla.init_params(CFG, jax.random.PRNGKey(1))
    tok = ActionTokenizer((-0.5,) * 6 + (-1.0,), (0.5,) * 6 + (1.0,), CFG.vocab_size)
    path = tmp_path_factory.mktemp("c") / "vla"
    checkpoint.save_policy(path, params, CFG, tok, text_vocab=language.VOCAB)
    return path, params, tok


def test_policy_checkpoint_round_trip(policy_ckpt):
    path, params, tok = policy_ckpt
    p2, cfg2, tok2, meta = checkpoint.load_policy(path)
    assert cfg2 == CFG and tok2 == tok and meta["kind"] == "vla"
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(p2)):
        np.testing.assert_array_equal(a, b)


def test_missing_checkpoint_names_the_path(tmp_path):
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint at .*nowhere"):
        checkpoint.load_policy(tmp_path / "nowhere")


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_truncated_checkpoint_is_refused(policy_ckpt, tmp_path):
    bad = _copy(policy_ckpt[0], tmp_path / "bad")
    files = [f for f in bad.rglob("*") if f.is_file() and "meta" not in str(f) and f.stat().st_size > 1000]
    assert files
    for f in files:
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 3])
    with pytest.raises(checkpoint.CheckpointError, match=str(bad.name)):
        checkpoint.load_policy(bad)


def test_mismatched_config_is_refused(policy_ckpt, tmp_path):
    bad = _copy(policy_ckpt[0], tmp_path / "mismatch")
    meta_files = [f for f in bad.rglob("metadata") if f.parent.name == "meta"]
    assert meta_files
    for f in meta_files:
        meta = json.loads(f.read_text())
        meta["config"]["d_model"] = 64
        f.write_text(json.dumps(meta))
    with pytest.raises(checkpoint.CheckpointError, match="not matching|does not match"):
        checkpoint.load_policy(bad)


def test_drafter_training_lowers_its_loss_and_its_checkpoint_is_tied_to_the_target(dataset, policy_ckpt, tmp_path):
    tparams = policy_ckpt[1]
    table = jax.device_put(data.load_steps(str(dataset)))
    tokens = training.greedy_tokens(tparams, CFG, table, batch=64)
    assert tokens.shape == (table.size, 7)
    cfg = training.TrainConfig(steps=40, batch_size=32, lr=3e-3, warmup_steps=5)
    state = training.init_drafter_state(CFG, cfg)
    step = training.make_drafter_step(CFG, cfg)
    ev = training.make_drafter_eval(CFG, 128, cfg)
    key = jax.random.PRNGKey(0)
    before, _ = ev(state.params, tparams, table, tokens, key)
    for _ in range(cfg.steps):
        state, _ = step(state, tparams, table, tokens, key)
    after, metrics = ev(state.params, tparams, table, tokens, key)
    assert float(after) < float(before) * 0.7, (float(before), float(after))
    assert metrics["top1"].shape == (6,)
    path = tmp_path / "drafter"
    checkpoint.save_drafter(path, state.params, CFG, tparams)
    dparams, meta = checkpoint.load_drafter(path, CFG, tparams)
    for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(dparams)):
        np.testing.assert_array_equal(a, b)
    other = jax.tree.map(lambda x: x + 1e-3, tparams)
    with pytest.raises(checkpoint.CheckpointError, match="another target"):
        checkpoint.load_drafter(path, CFG, other)
    with pytest.raises(checkpoint.CheckpointError, match="not a VLA policy"):
        checkpoint.load_policy(path)


def test_a_seed_fixes_the_initialisation_and_the_minibatch_order(dataset):
    table = jax.device_put(data.load_steps(str(dataset)))
    tok = ActionTokenizer.fit(np.asarray(table.action), CFG.vocab_size)

    def run(seed):
        cfg = training.TrainConfig(steps=3, batch_size=16, lr=3e-3, warmup_steps=1, image_shift=2, seed=seed)
        state, step = training.init_state(CFG, cfg), training.make_train_step(CFG, cfg, tok)
        key = jax.random.PRNGKey(cfg.seed + 1)  # as experiments.train draws it
        for _ in range(cfg.steps):
            state, _ = step(state, table, key)
        return jax.tree.leaves(state.params)

    a, b, c = run(0), run(0), run(1)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert any(not np.array_equal(x, z) for x, z in zip(a, c))
