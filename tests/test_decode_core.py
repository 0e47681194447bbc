"""The decode core imports and decodes without the simulator, and its text constants agree
with the env's vocabulary."""

import ast
import dataclasses
import json
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import envs.env
from envs import language
from heisd_jax import observation, vla

CORE = ("tokenizer", "observation", "vla", "drafter", "spec_decode", "retrieval", "acceptance", "kinematics", "hybrid",
        "budget", "checkpoint")

CHILD = """
import json, os, sys
flags = os.environ.get("XLA_FLAGS")
import heisd_jax
from heisd_jax import {core}
import jax, jax.numpy as jnp, numpy as np
cfg = vla.VLAConfig(image_size=16, patch_size=8, vision_layers=1, d_model=32, n_layers=1, n_heads=4, mlp_dim=64)
params = vla.init_params(cfg, jax.random.PRNGKey(0))
obs = heisd_jax.Observation(image=np.zeros((2, *cfg.image_shape), np.uint8),
                            instruction=np.ones((2, cfg.text_len), np.int32), proprio=np.zeros((2, 8), np.float32))
tokens, stats = heisd_jax.decode_action(params, cfg, obs)
print(json.dumps(dict(sim=sorted(m for m in sys.modules if m.split(".")[0] in ("envs", "mujoco")),
                      flags_kept=os.environ.get("XLA_FLAGS") == flags, shape=list(tokens.shape),
                      passes=np.asarray(stats["target_passes"]).tolist())))
"""


def test_decode_core_runs_without_envs_mujoco_or_xla_flag_changes():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # unset: any flag an import adds would show
    env["JAX_PLATFORMS"] = "cpu"
    r = subprocess.run([sys.executable, "-c", CHILD.format(core=", ".join(CORE))], env=env, capture_output=True,
                       text=True, timeout=300, cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["sim"] == []
    assert out["flags_kept"]
    assert out["shape"] == [2, 7] and out["passes"] == [7.0, 7.0]


def test_text_constants_match_the_env_vocabulary():
    cfg = vla.VLAConfig()
    assert cfg.text_vocab == len(language.VOCAB) == observation.TEXT_VOCAB
    assert cfg.text_len == language.MAX_INSTRUCTION_TOKENS == observation.TEXT_LEN
    assert language.WORD_TO_ID[language.PAD] == observation.PAD_ID
    assert language.to_ids("pick up the red block")[-1] == observation.PAD_ID


def test_unknown_instruction_words_are_unk_or_refused_as_asked():
    ids = language.to_ids("pick up the orange block")
    assert language.WORD_TO_ID[language.UNK] in ids.tolist()
    with pytest.raises(ValueError, match=r"words outside the vocabulary: \['orange'\]"):
        language.to_ids("pick up the orange block", unknown="error")
    np.testing.assert_array_equal(language.to_ids("pick up the red block", unknown="error"),
                                  language.to_ids("pick up the red block"))
    with pytest.raises(ValueError, match="valid: unk, error"):
        language.to_ids("pick up the red block", unknown="ignore")


def test_env_and_model_observations_agree_field_for_field():
    from heisd_jax.harness import vla_policy  # the evaluation layer: it converts one into the other

    assert vla.Observation is observation.Observation and envs.env.Observation is not vla.Observation
    names = lambda cls: [f.name for f in dataclasses.fields(cls)]  # noqa: E731
    assert names(envs.env.Observation) == names(vla.Observation)
    env_obs = envs.env.Observation(image=np.zeros((1, 4, 4, 3), np.uint8), instruction=np.ones((1, 20), np.int32),
                                   proprio=np.zeros((1, 8), np.float32))
    got = vla_policy.observation(types.SimpleNamespace(obs=env_obs))
    assert isinstance(got, vla.Observation) and got.instruction is env_obs.instruction


def _imports(path: Path, package: str) -> set[str]:
    """The modules of `package` that file `path` imports, at any depth of the file."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == package}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == package:
            out |= {f"{node.module}.{a.name}" if node.module == package else node.module for a in node.names}
    return out


def test_heisd_jax_has_no_import_cycles():  # the layers themselves: tests/test_layers.py
    root = Path(__file__).resolve().parents[1]
    graph = {}
    for path in (root / "heisd_jax").rglob("*.py"):
        name = ".".join(path.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
        graph[name] = {m for m in _imports(path, "heisd_jax") if m != name}

    def cycle_from(node, seen):
        for nxt in graph.get(node, ()):
            if nxt in seen:
                return seen[seen.index(nxt):] + [nxt]
            found = cycle_from(nxt, seen + [nxt])
            if found:
                return found
        return None
    for node in graph:
        assert cycle_from(node, [node]) is None, " -> ".join(cycle_from(node, [node]))
