"""The executable store (heisd_jax.harness.executable_store): keys that change with what makes a program
and only with it, entries that survive a fresh process (XLA:CPU's two traps included), and a
bad entry read as a miss."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heisd_jax.harness import executable_store as xs

ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class _Config:
    size: int = 3
    scale: float = 0.5
    names: tuple = ("a", "b")


def test_description_is_stable_and_follows_every_field():
    base = xs.describe({"cfg": _Config(), "table": np.arange(4.0), "path": Path("x")})
    assert base == xs.describe({"path": Path("x"), "table": np.arange(4.0), "cfg": _Config()})  # dict order
    for changed in ({"cfg": _Config(size=4)}, {"cfg": _Config(scale=0.25)}, {"cfg": _Config(names=("a",))},
                    {"table": np.arange(4.0) + 1e-6}, {"table": np.arange(4, dtype=np.float32)}, {"path": Path("y")}):
        other = {"cfg": _Config(), "table": np.arange(4.0), "path": Path("x"), **changed}
        assert xs.describe(other) != base, changed


def test_an_object_without_a_stable_description_keys_nothing(tmp_path):
    with pytest.raises(xs.Undescribable):
        xs.describe({"fn": lambda x: x})
    assert xs.ExecutableStore(tmp_path).key({"fn": object()}, (np.zeros(2),)) is None


def test_key_follows_identity_inputs_and_flags(tmp_path, monkeypatch):
    store = xs.ExecutableStore(tmp_path)
    x = (np.zeros((2, 3), np.float32), {"p": np.ones(4, np.float32)})
    k = store.key({"method": "ar"}, x)
    assert k == store.key({"method": "ar"}, (np.ones((2, 3), np.float32), {"p": np.zeros(4, np.float32)}))  # values: no
    assert k != store.key({"method": "expert"}, x)
    assert k != store.key({"method": "ar"}, (np.zeros((2, 4), np.float32), x[1]))
    assert k != store.key({"method": "ar"}, (np.zeros((2, 3), np.int32), x[1]))
    assert k != store.key({"method": "ar"}, (x[0], {"q": x[1]["p"]}))
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    k2 = store.key({"method": "ar"}, x)
    assert k2 != k
    results = tmp_path / "autotune.txt"  # a file an XLA flag names: its bytes count, not just its name
    results.write_text("one")
    monkeypatch.setenv("XLA_FLAGS", os.environ["XLA_FLAGS"] + f" --xla_gpu_load_autotune_results_from={results}")
    k3 = store.key({"method": "ar"}, x)
    results.write_text("two")
    assert len({k2, k3, store.key({"method": "ar"}, x)}) == 3


def test_file_digest_reads_contents_and_names(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        (d / "sub").mkdir(parents=True)
        (d / "sub" / "w.bin").write_bytes(b"weights")
    assert xs.file_digest(a) == xs.file_digest(b)
    (b / "sub" / "w.bin").write_bytes(b"weightz")
    assert xs.file_digest(a) != xs.file_digest(b)
    (b / "sub" / "w.bin").rename(b / "sub" / "v.bin")
    (b / "sub" / "v.bin").write_bytes(b"weights")
    assert xs.file_digest(a) != xs.file_digest(b)
    with pytest.raises(FileNotFoundError):
        xs.file_digest(tmp_path / "missing")


def _program(x):  # a LAPACK call on a CPU (Cholesky), as MJX's constraint solver makes
    m = x @ x.T + 3.0 * jnp.eye(x.shape[0])
    return jnp.linalg.cholesky(m).sum(axis=1) + jnp.sin(x).mean()


_SCRIPT = """
import sys, numpy as np, jax, jax.numpy as jnp
from experiments import cli
from heisd_jax.harness import executable_store as xs
from tests.test_executable_store import _program
mode, store_dir, cache = sys.argv[1:4]
cli.setup_compilation_cache(cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
store, x = xs.ExecutableStore(store_dir), np.linspace(-1.0, 1.0, 12, dtype=np.float32).reshape(4, 3)
key = store.key({"program": "cholesky"}, (x,))
if mode == "warm":
    jax.jit(_program)(x).block_until_ready()  # compiled and written to JAX's cache
elif mode == "save":
    assert store.load(key) is None
    assert store.save(key, xs.compile_storable(jax.jit(_program).trace(x).lower()))
else:
    compiled = store.load(key)
    assert compiled is not None
    print(np.asarray(compiled(x)).tobytes().hex())
"""


def _run(*args):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", _SCRIPT, *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip()


def test_a_stored_program_runs_in_a_fresh_process(tmp_path):
    """Saved by a process whose JAX compilation cache already held the program (so that a plain
    compile would load it, and store it without its kernels), loaded by another that lowers
    nothing (so that LAPACK's kernels are not initialized by lowering): the same result."""
    cache, store = tmp_path / "cache", tmp_path / "store"
    _run("warm", store, cache)
    assert any(p.name.startswith("jit__program") for p in cache.iterdir())
    _run("save", store, cache)
    x = np.linspace(-1.0, 1.0, 12, dtype=np.float32).reshape(4, 3)
    assert _run("load", store, cache) == np.asarray(jax.jit(_program)(x)).tobytes().hex()


def test_a_bad_entry_is_a_miss_and_is_rewritten(tmp_path):
    store = xs.ExecutableStore(tmp_path)
    x = np.ones((4, 3), np.float32)
    key = store.key({"program": "cholesky"}, (x,))
    store.path(key).write_bytes(b"truncated")
    assert store.load(key) is None
    assert store.save(key, xs.compile_storable(jax.jit(_program).trace(x).lower()))
    np.testing.assert_array_equal(np.asarray(store.load(key)(x)), np.asarray(jax.jit(_program)(x)))
    assert [p.name for p in tmp_path.iterdir()] == [store.path(key).name]  # no temporary left behind


def test_compile_or_load_traces_once_per_key(tmp_path):
    """The first call compiles and stores; a second with the same identity and input shapes
    loads without tracing and computes the same; another identity, or no store, compiles."""
    traces = []

    def fresh():  # a new function each time, so that JAX's in-memory trace cache cannot answer
        def program(x):
            traces.append(1)
            return _program(x)
        return jax.jit(program)

    store, x = xs.ExecutableStore(tmp_path), np.linspace(-1.0, 1.0, 12, dtype=np.float32).reshape(4, 3)
    first, hit = xs.compile_or_load(store, {"program": "cholesky"}, fresh(), (x,))
    assert not hit and len(traces) == 1
    second, hit = xs.compile_or_load(store, {"program": "cholesky"}, fresh(), (x,))
    assert hit and len(traces) == 1
    np.testing.assert_array_equal(np.asarray(second(x)), np.asarray(first(x)))
    assert not xs.compile_or_load(store, {"program": "other"}, fresh(), (x,))[1] and len(traces) == 2
    assert not xs.compile_or_load(store, {"program": "cholesky"}, fresh(), (x[:3],))[1] and len(traces) == 3
    assert not xs.compile_or_load(None, {"program": "cholesky"}, fresh(), (x,))[1] and len(traces) == 4


def _run_entry_point(cmd: list[str], *more: str) -> str:
    """An entry point run in its own process from the repository root; its stdout."""
    out = subprocess.run([*cmd, *more], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                         text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


@pytest.mark.slow
def test_a_warm_collection_loads_its_program_and_writes_the_same_dataset(tmp_path):
    """collect_demos keys its program by what makes it (a DAgger round's policy parameters are
    an input), so a second collection with the same settings loads it and writes the same
    episodes and labels."""
    from envs import demos  # noqa: PLC0415

    cmd = [sys.executable, "-m", "experiments.collect_demos", "--suites=spatial", "--tasks=left_block_plate",
           "--episodes_per_task=2", "--num_envs=2", "--image_size=16", "--compilation_cache=",
           f"--executable_store={tmp_path / 'store'}"]
    logs = [_run_entry_point(cmd, f"--out={tmp_path / f'd{i}'}") for i in range(2)]
    assert "(1 programs, 0 loaded from the executable store)" in logs[0], logs[0]
    assert "(1 programs, 1 loaded from the executable store)" in logs[1], logs[1]
    one, two = demos.DemoDataset(tmp_path / "d0"), demos.DemoDataset(tmp_path / "d1")
    assert one.episodes == two.episodes and len(one.episodes) == 2
    for i in range(2):
        a, b = one.episode(i), two.episode(i)
        assert all(np.array_equal(a[f], b[f]) for f in a)


@pytest.mark.slow
def test_a_warm_evaluation_loads_its_rollout_and_runs_the_same_episodes(tmp_path):
    # 3 episodes in 2 slots: a queue, so several programs
    cmd = [sys.executable, "-m", "experiments.evaluate", "--method=expert", "--suites=spatial",
           "--tasks=left_block_plate", "--episodes=3", "--num_envs=2", "--compilation_cache=",
           f"--executable_store={tmp_path / 'store'}"]
    runs = [(_run_entry_point(cmd, f"--out={tmp_path / f'{i}.json'}"), json.loads((tmp_path / f"{i}.json").read_text()))
            for i in range(2)]
    assert "loaded from the executable store" not in runs[0][0] and "loaded from the executable store" in runs[1][0]
    first, second = (r[1]["timing"]["compile_split"] for r in runs)
    programs = ("starts", "first", "physics", "turn")  # the queue's, the env's step split at its stages
    assert {k.rsplit("_", 1)[0] for k in first} == set(programs) and "trace" not in first
    assert all(first[f"{p}_trace"] > 0.0 and f"{p}_store" in first for p in programs)
    assert all(second[f"{p}_{s}"] == 0.0 for p in programs for s in ("trace", "lower", "xla"))
    assert runs[0][1]["episodes"] == runs[1][1]["episodes"]


@pytest.mark.slow
def test_the_resets_and_physics_programs_are_shared_by_rollouts_of_other_policies_on_the_same_env(tmp_path):
    """The starts (the resets) and an env stage's program (the physics) read no policy, so a
    rollout of another policy, stored under another caller, loads them; its own it compiles."""
    from envs import expert, tasks  # noqa: PLC0415
    from envs.env import EnvConfig, TabletopEnv  # noqa: PLC0415
    from heisd_jax.harness import evaluator as ev  # noqa: PLC0415

    env = TabletopEnv(tasks.get_tasks("spatial", ["left_block_plate"]), EnvConfig(render=False))
    splits = []
    for name in ("expert", "expert, renamed"):
        rollout = ev.BatchRollout(env, dataclasses.replace(expert.policy(env), name=name), num_envs=2, queue=3,
                                  store=xs.ExecutableStore(tmp_path, {"method": name}))
        rollout.compile(rollout.inputs(np.zeros(3, np.int32), np.arange(3)))
        splits.append(rollout.compile_split)
    first, second = splits
    for part in ("starts", "physics"):
        assert first[f"{part}_trace"] > 0.0 and second[f"{part}_trace"] == second[f"{part}_xla"] == 0.0
    assert all(second[f"{p}_trace"] > 0.0 for p in ("first", "turn"))


def test_the_store_keeps_within_its_size_by_dropping_the_least_recently_used(tmp_path):
    x = np.ones((4, 3), np.float32)
    compiled = xs.compile_storable(jax.jit(_program).trace(x).lower())
    probe = xs.ExecutableStore(tmp_path / "probe")
    probe.save("probe", compiled)
    size = probe.path("probe").stat().st_size
    store = xs.ExecutableStore(tmp_path / "store", max_bytes=int(2.5 * size))  # room for two entries
    for i, key in enumerate(("a", "b")):
        assert store.save(key, compiled)
        os.utime(store.path(key), (1000.0 + i, 1000.0 + i))  # a older than b
    assert store.load("a") is not None  # a load renews a: b is now the least recently used
    assert store.save("c", compiled)
    assert sorted(p.stem for p in store.directory.glob(f"*{xs.SUFFIX}")) == ["a", "c"]
    tiny = xs.ExecutableStore(tmp_path / "store", max_bytes=1)  # even too small, the new entry stays
    assert tiny.save("d", compiled)
    assert [p.stem for p in tiny.directory.glob(f"*{xs.SUFFIX}")] == ["d"]


def test_bypassing_the_cache_nests_across_threads():
    """Compiles in several threads bypass JAX's cache together: it stays off until the last
    leaves, then the setting found by the first is restored, in whatever order they leave."""
    before = jax.config.jax_enable_compilation_cache
    a, b = xs.jax_cache_bypassed(), xs.jax_cache_bypassed()
    a.__enter__()
    b.__enter__()
    assert not jax.config.jax_enable_compilation_cache
    a.__exit__(None, None, None)  # the first to enter leaves first
    assert not jax.config.jax_enable_compilation_cache
    b.__exit__(None, None, None)
    assert jax.config.jax_enable_compilation_cache == before


def test_checkpoints_that_differ_only_in_weights_lower_to_one_program(tmp_path):
    """Why `ar` leaves its checkpoint's digest out of the store's key (`Method.shares_programs`):
    two checkpoints of one architecture and tokenizer, other weights, lower to the same rollout
    program (its constants included), with equal meta; a checkpoint with other tokenizer bins
    (constants in the program) lowers to another, and its meta, which the key holds, differs."""
    import tiny_models  # noqa: PLC0415
    from envs import language, rollout, tasks  # noqa: PLC0415
    from envs.env import TabletopEnv  # noqa: PLC0415
    from heisd_jax import checkpoint, vla  # noqa: PLC0415
    from heisd_jax.harness import methods  # noqa: PLC0415
    from heisd_jax.tokenizer import ActionTokenizer  # noqa: PLC0415

    cfg = tiny_models.CFG
    made = {"a": (0, 1.0), "b": (1, 1.0), "other_bins": (0, 0.5)}
    for name, (seed, bound) in made.items():
        tok = ActionTokenizer(q01=(-bound,) * 7, q99=(bound,) * 7, vocab_size=cfg.vocab_size)
        checkpoint.save_policy(tmp_path / name, vla.init_params(cfg, jax.random.PRNGKey(seed)), cfg, tok,
                               text_vocab=tuple(language.VOCAB))
    env = TabletopEnv(tasks.get_tasks("spatial", ["left_block_plate"]), methods.env_config("ar", tmp_path / "a"))
    tids = np.zeros(2, np.int32)
    keys = env.initial_state_keys(tids, np.arange(2))

    def lowered(name):
        policy = methods.make_policy("ar", env, checkpoint=tmp_path / name)

        def run(params, k, t):
            return rollout.run_episodes(env, dataclasses.replace(policy, params=params), k, t, 3, 0)

        return jax.jit(run).lower(policy.params, keys, jnp.asarray(tids)).as_text(), xs.describe(policy.meta)

    lowered("a")  # the first trace fills JAX's tracing caches, which rename shared functions in later ones
    (a, meta_a), (b, meta_b), (other, meta_other) = (lowered(n) for n in made)
    assert a == b and meta_a == meta_b
    assert a != other and meta_a != meta_other
    assert methods.get("ar").shares_programs == ("checkpoint",)
