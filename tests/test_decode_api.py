"""The public decode call (`heisd_jax.decode_action`, `spec_decode.decode_action`): its documented example runs, it equals the
decoding functions it wraps, and bad observations fail at the boundary with the field,
the given and the expected shape."""

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heisd_jax
import tiny_models
from heisd_jax import spec_decode, target_model, vla
from heisd_jax.tokenizer import INVALID_ID, ActionTokenizer

ROOT = Path(__file__).resolve().parents[1]
CFG = tiny_models.CFG  # image [16, 16, 3], text_len 20, text_vocab 36, proprio 8


def test_documented_example_decodes_the_shipped_checkpoint(monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "decode_api.md").read_text(), re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(ROOT)
    ns = {}
    exec(compile(blocks[0], "docs/decode_api.md", "exec"), ns)  # noqa: S102
    tokens, cfg, b = ns["tokens"], ns["cfg"], ns["B"]
    assert tokens.shape == (b, 7) and tokens.dtype == jnp.int32
    bins = np.asarray(tokens) - cfg.first_action_id
    assert np.all((bins >= 0) & (bins < 256))
    assert ns["actions"].shape == (b, 7) and np.all(np.abs(np.asarray(ns["actions"])) <= 1.0)
    assert np.all(np.asarray(ns["stats"]["target_passes"]) == 7)
    np.testing.assert_array_equal(ns["sd_tokens"], tokens)  # strict speculative decoding == AR
    assert np.all(np.asarray(ns["sd_stats"]["target_passes"]) <= 7)


def test_readme_example_decodes_the_shipped_checkpoint(monkeypatch):
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"## Decoding in your own JAX code\n\n((?:    .*\n)+)", readme).group(1)
    monkeypatch.chdir(ROOT)
    ns = {}
    exec(compile("\n".join(line[4:] for line in block.splitlines()), "README.md", "exec"), ns)  # noqa: S102
    assert ns["tokens"].shape == (2, 7) and ns["actions"].shape == (2, 7)
    assert np.all(np.abs(np.asarray(ns["actions"])) <= 1.0)
    assert np.all(np.asarray(ns["stats"]["target_passes"]) == 7)


def test_decode_action_equals_ar_and_strict_speculative_decoding(tiny_hybrid):
    params, obs, ar_tokens = tiny_hybrid
    tokens, stats = heisd_jax.decode_action(params["target"], CFG, obs)
    np.testing.assert_array_equal(tokens, ar_tokens)
    assert tokens.dtype == jnp.int32 and set(stats) == {"target_passes", "tokens", "invalid"}
    assert not np.asarray(stats["invalid"]).any()
    assert stats["target_passes"].shape == (obs.image.shape[0],)
    spec = spec_decode.SpecConfig(top_k=4, depth=3, total_tokens=8)
    sd, sd_stats = heisd_jax.decode_action(params, CFG, obs, spec=spec)
    np.testing.assert_array_equal(sd, ar_tokens)
    assert {"target_passes", "drafter_passes", "rounds", "tokens"} <= set(sd_stats)


def _obs(b=2, **override):
    o = tiny_models.obs(0, batch=b)
    return o.replace(**{k: jnp.asarray(v) for k, v in override.items()})


IMG = r"observation.image has shape \[{}\], expected \[B, 16, 16, 3\]"
NON_FINITE = r"observation.proprio has non-finite values \(NaN/inf\) in rows "
BAD_IDS = r"observation.instruction has token ids in \[{0}, {0}\], expected \[0, 36\) \(text_vocab\)"


@pytest.mark.parametrize("override, message", [
    (dict(image=np.zeros((2, 32, 32, 3), np.uint8)), IMG.format("2, 32, 32, 3") + "$"),
    (dict(image=np.zeros((2, 3, 16, 16), np.uint8)), IMG.format("2, 3, 16, 16") + r" \(channels first"),
    (dict(image=np.zeros((16, 16, 3), np.uint8)), IMG.format("16, 16, 3")),
    (dict(instruction=np.ones((2, 12), np.int32)), r"observation.instruction has shape \[2, 12\], expected \[B, 20\]"),
    (dict(proprio=np.zeros((2, 7), np.float32)), r"observation.proprio has shape \[2, 7\], expected \[B, 8\]"),
    (dict(proprio=np.zeros((3, 8), np.float32)),
     r"disagree on the batch size B: image \[2, 16, 16, 3\], instruction \[2, 20\], proprio \[3, 8\]"),
    (dict(image=np.zeros((2, 16, 16, 3), np.float32)), r"observation.image has dtype float32, expected uint8"),
    (dict(proprio=np.array([[0.0] * 8, [np.nan] + [0.0] * 7], np.float32)), NON_FINITE + r"\[1\]"),
    (dict(proprio=np.full((2, 8), np.inf, np.float32)), NON_FINITE + r"\[0, 1\]"),
    (dict(instruction=np.full((2, 20), 36, np.int32)), BAD_IDS.format(36)),
    (dict(instruction=np.full((2, 20), -1, np.int32)), BAD_IDS.format(-1)),
])
def test_bad_observations_are_refused_naming_the_field(override, message):
    with pytest.raises(ValueError, match=message):
        vla.check_observation(CFG, _obs(**override))


def test_decode_entries_check_before_the_model():
    params = jax.eval_shape(lambda: vla.init_params(CFG, jax.random.PRNGKey(0)))  # never reached
    bad = _obs(image=np.zeros((2, 3, 16, 16), np.uint8))
    for call in (lambda: heisd_jax.decode_action(params, CFG, bad), lambda: target_model.ar_decode(params, CFG, bad)):
        with pytest.raises(ValueError, match="observation.image has shape"):
            call()
    with pytest.raises(TypeError, match="Observation"):
        vla.check_observation(CFG, {"image": bad.image})


def test_value_checks_skip_tracers_and_shape_checks_do_not():
    nan = _obs(proprio=np.full((2, 8), np.nan, np.float32))
    assert jax.jit(lambda o: jnp.asarray(vla.check_observation(CFG, o)))(nan) == 2
    with pytest.raises(ValueError, match="observation.proprio has shape"):
        jax.jit(lambda o: vla.check_observation(CFG, o))(_obs(proprio=np.zeros((2, 9), np.float32)))
    assert vla.check_observation(CFG, _obs()) == 2


def test_decode_action_inside_a_callers_jit_equals_the_top_level_call(tiny_hybrid):
    """At top level the decode step is compiled with the device-loop options, which JAX takes
    on a top-level jit only; inside a caller's jit or grad, with the observation an argument or
    a closed-over constant, the same step becomes part of the caller's program."""
    params, obs, ar_tokens = tiny_hybrid
    spec = spec_decode.SpecConfig(top_k=4, depth=3, total_tokens=8)
    for p, s in ((params["target"], None), (params, spec)):
        want = heisd_jax.decode_action(p, CFG, obs, spec=s)[0]
        np.testing.assert_array_equal(want, ar_tokens)
        as_argument = jax.jit(lambda o, p=p, s=s: heisd_jax.decode_action(p, CFG, o, spec=s)[0])(obs)
        closed_over = jax.jit(lambda p=p, s=s: heisd_jax.decode_action(p, CFG, obs, spec=s)[0])()
        np.testing.assert_array_equal(as_argument, want)
        np.testing.assert_array_equal(closed_over, want)
    proprio_grad = jax.grad(lambda x: heisd_jax.decode_action(
        params["target"], CFG, obs.replace(proprio=x))[1]["target_passes"].sum())(obs.proprio)
    assert proprio_grad.shape == obs.proprio.shape


def test_invalid_rows_under_jit_decode_to_the_zero_action_and_are_counted(tiny_hybrid):
    """Under an outer jit the value checks cannot raise: a row with NaN proprio or an
    out-of-vocabulary instruction id gets INVALID_ID tokens (the zero action) and
    stats["invalid"] = 1; the other rows decode as they would alone."""
    params, obs, ar_tokens = tiny_hybrid
    b = obs.image.shape[0]
    assert b >= 3
    proprio = np.array(obs.proprio).copy()
    proprio[0, 2] = np.nan
    instruction = np.array(obs.instruction).copy()
    instruction[1, 3] = CFG.text_vocab
    bad = obs.replace(proprio=jnp.asarray(proprio), instruction=jnp.asarray(instruction))
    spec = spec_decode.SpecConfig(top_k=4, depth=3, total_tokens=8)
    for p, s in ((params["target"], None), (params, spec)):
        tokens, stats = jax.jit(lambda o, p=p, s=s: heisd_jax.decode_action(p, CFG, o, spec=s))(bad)
        tokens = np.asarray(tokens)
        np.testing.assert_array_equal(tokens[:2], np.full((2, 7), INVALID_ID))
        np.testing.assert_array_equal(tokens[2:], np.asarray(ar_tokens)[2:])
        np.testing.assert_array_equal(stats["invalid"], [1.0, 1.0] + [0.0] * (b - 2))
    tok = ActionTokenizer(q01=(-0.5,) * 7, q99=(0.5,) * 7, vocab_size=CFG.vocab_size)
    actions = np.asarray(tok.to_actions(jnp.asarray(tokens)))
    np.testing.assert_array_equal(actions[:2], 0.0)
    np.testing.assert_array_equal(actions[2:], np.asarray(tok.to_actions(ar_tokens))[2:])
    with pytest.raises(ValueError, match="non-finite"):  # outside jit the same input is refused
        heisd_jax.decode_action(params["target"], CFG, bad)
