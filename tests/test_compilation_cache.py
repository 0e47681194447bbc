"""The persistent compilation cache every entry point sets up (experiments.cli): where it
lives by default, that compiled programs land there, and that '' turns it off."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from jax.experimental.compilation_cache import compilation_cache

from experiments import cli

ROOT = Path(__file__).resolve().parents[1]
OPTIONS = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
           "jax_persistent_cache_min_entry_size_bytes")


@pytest.fixture
def restore_cache():
    """The rest of the test session keeps the cache settings it had."""
    before = {k: getattr(jax.config, k) for k in OPTIONS}
    yield
    for k, v in before.items():
        jax.config.update(k, v)
    compilation_cache.reset_cache()


def _entries(path: Path) -> list[Path]:
    return [p for p in path.rglob("*") if p.is_file() and not p.name.startswith(".")]


def test_default_location_follows_the_environment(monkeypatch, tmp_path):
    for var in ("JAX_COMPILATION_CACHE_DIR", "HEISD_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    assert cli.default_compilation_cache() == str(Path.home() / ".cache" / "heisd_jax" / "jax_compilation_cache")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cli.default_compilation_cache() == str(tmp_path / "xdg" / "heisd_jax" / "jax_compilation_cache")
    monkeypatch.setenv("HEISD_CACHE", str(tmp_path / "heisd"))
    assert cli.default_compilation_cache() == str(tmp_path / "heisd" / "jax_compilation_cache")
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "jax"))
    assert cli.default_compilation_cache() == str(tmp_path / "jax")
    from envs import _xla
    from heisd_jax import cache_dirs

    for var in ("JAX_COMPILATION_CACHE_DIR", "HEISD_CACHE", "XDG_CACHE_HOME"):  # envs keeps its own copy: the same
        assert _xla.cache_root() == cache_dirs.cache_root()
        monkeypatch.delenv(var)
    assert _xla.cache_root() == cache_dirs.cache_root()


def test_compiled_programs_are_written_to_the_cache(tmp_path, restore_cache):
    cache = tmp_path / "cache"
    assert cli.setup_compilation_cache(cache) == str(cache)
    assert jax.config.jax_compilation_cache_dir == str(cache)
    assert jax.config.jax_persistent_cache_min_compile_time_secs == cli.MIN_COMPILE_SECONDS
    assert jax.config.jax_persistent_cache_min_entry_size_bytes == -1
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # a tiny program compiles in ms
    jax.jit(lambda x: jnp.sin(x) * 3.25 + 0.5)(jnp.arange(7.0)).block_until_ready()
    assert _entries(cache)


def test_empty_path_turns_the_cache_off(tmp_path, restore_cache):
    assert cli.setup_compilation_cache("") is None
    assert jax.config.jax_compilation_cache_dir is None
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.jit(lambda x: jnp.cos(x) * 1.75 - 0.25)(jnp.arange(5.0)).block_until_ready()
    assert not _entries(tmp_path)


# An entry point: cli.run sets the cache up from --compilation_cache before main compiles.
SCRIPT = """
import jax, jax.numpy as jnp
from experiments import cli
def main(argv):
    jax.jit(lambda x: jnp.tanh(x) * 2.5)(jnp.arange(3.0)).block_until_ready()
    print("cache:", jax.config.jax_compilation_cache_dir)
cli.run(main)
"""


def test_entry_points_set_the_cache_from_the_flag(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    cache = tmp_path / "cache"
    r = subprocess.run([sys.executable, "-c", SCRIPT, f"--compilation_cache={cache}"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"cache: {cache}" in r.stdout and _entries(cache)
    off = tmp_path / "off"
    r = subprocess.run([sys.executable, "-c", SCRIPT, "--compilation_cache="], cwd=ROOT, env=dict(env, JAX_COMPILATION_CACHE_DIR=str(off)),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "cache: None" in r.stdout and not off.exists()
