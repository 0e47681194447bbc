"""The packages are layers with arrows one way: the decode core (the models, the target-model
interface, the decoders and their rules) imports nothing of the simulator, and `envs` imports
nothing of `heisd_jax`. Each is checked in a fresh interpreter, whose `sys.modules` then
tells what an import pulled in."""

import ast
import os
import subprocess
import sys

import pytest

DECODE_CORE = ("vla", "tokenizer", "observation", "target_model", "drafter", "spec_decode", "acceptance",
               "retrieval", "kinematics", "budget", "hybrid", "cost_model", "scale", "checkpoint", "sharding")
ENVS = ("env", "rollout", "tasks", "expert", "demos", "camera", "language")


def _imported(modules: list[str], prefix: str) -> list[str]:
    code = (f"import sys\nfor m in {modules!r}: __import__(m)\n"
            f"print(sorted(m for m in sys.modules if m == {prefix!r} or m.startswith({prefix + '.'!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})
    return ast.literal_eval(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("modules,other", [([f"heisd_jax.{m}" for m in DECODE_CORE], "envs"),
                                           ([f"envs.{m}" for m in ENVS], "heisd_jax")])
def test_a_layer_imports_nothing_of_the_other(modules, other):
    assert _imported(modules, other) == []
