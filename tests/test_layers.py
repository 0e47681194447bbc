"""The packages are layers with arrows one way: the decode core (every module directly in
`heisd_jax`: the models, the target-model interface, the decoders and their rules, the
utilities) imports nothing of the simulator nor of the harness above it, `envs` imports
nothing of `heisd_jax`, and the harness nothing of the entry points. Each is checked in a
fresh interpreter, whose `sys.modules` then tells what an import pulled in; no module imports
the project's own inside a function, where that check would not see it."""

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DECODE_CORE = sorted(p.stem for p in (ROOT / "heisd_jax").glob("*.py") if p.stem != "__init__")
HARNESS = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts) for p in (ROOT / "heisd_jax" / "harness").rglob("*.py")
                 if p.stem != "__init__")
ENVS = sorted(p.stem for p in (ROOT / "envs").glob("*.py") if p.stem != "__init__")


def _imported(modules: list[str], prefixes: tuple[str, ...]) -> list[str]:
    code = (f"import sys\nfor m in {modules!r}: __import__(m)\n"
            f"print(sorted(m for m in sys.modules if any(m == p or m.startswith(p + '.') for p in {prefixes!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})
    return ast.literal_eval(out.stdout.strip().splitlines()[-1])


def test_the_layers_are_found():
    assert {"vla", "target_model", "hybrid", "spec_decode"} <= set(DECODE_CORE) and "methods" not in DECODE_CORE
    assert {"heisd_jax.harness.methods", "heisd_jax.harness.evaluator", "heisd_jax.harness.offline.datastore"} <= set(HARNESS)
    assert {"env", "rollout", "tasks"} <= set(ENVS)


@pytest.mark.parametrize("modules,others", [([f"heisd_jax.{m}" for m in DECODE_CORE], ("envs", "heisd_jax.harness",
                                                                                      "experiments")),
                                            ([f"envs.{m}" for m in ENVS], ("heisd_jax", "experiments")),
                                            (HARNESS, ("experiments",))],
                         ids=["decode core", "envs", "harness"])
def test_a_layer_imports_nothing_above_or_beside_it(modules, others):
    assert _imported(modules, others) == []


PROJECT = ("heisd_jax", "envs", "experiments")


def _project_module(node) -> bool:
    names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
    return (isinstance(node, ast.ImportFrom) and node.level > 0) or any(n.split(".")[0] in PROJECT for n in names)


def test_no_function_level_imports():
    """An import of the project's own inside a function hides an arrow from the checks above
    until it runs (third-party ones are allowed: some must wait until XLA's flags are set)."""
    found = []
    for path in [*(ROOT / "heisd_jax").rglob("*.py"), *(ROOT / "envs").rglob("*.py")]:
        for fn in ast.walk(ast.parse(path.read_text())):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                found += [f"{path.relative_to(ROOT)}:{n.lineno}" for n in ast.walk(fn)
                          if isinstance(n, (ast.Import, ast.ImportFrom)) and _project_module(n)]
    assert not found, f"function-level imports: {found}"
