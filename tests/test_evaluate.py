"""The batched evaluator with a VLA decoding method, end to end, and the shipped checkpoint."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from envs import language, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from heisd_jax import checkpoint, results_io, target_model, vla
from heisd_jax.harness import evaluator as ev, methods, vla_policy
from heisd_jax.tokenizer import ActionTokenizer

# Tiny, but at the env camera's 64 px so it plugs into the real evaluator.
CFG = vla.VLAConfig(image_size=64, patch_size=16, vision_layers=1, d_model=32, n_layers=2, n_heads=4, mlp_dim=64,
                    cache_slots=48)
TASKS = "left_block_plate,pick_red_block"


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    path = tmp_path_factory.mktemp("ar") / "vla"
    tok = ActionTokenizer((-1.0,) * 7, (1.0,) * 7, CFG.vocab_size)
    checkpoint.save_policy(path, vla.init_params(CFG, jax.random.PRNGKey(3)), CFG, tok, text_vocab=language.VOCAB)
    return path


def _run_main(argv):
    """The entry point in its own process (absl flags are process-global)."""
    out = subprocess.run([sys.executable, "-m", "experiments.evaluate", *argv], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1], timeout=1200)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


@pytest.mark.slow  # two evaluations, each in its own process (compiles the AR rollout)
def test_ar_evaluation_writes_a_well_formed_result_file_and_resumes(tiny_ckpt, tmp_path):
    out = tmp_path / "ar.json"
    argv = ["--method=ar", f"--checkpoint={tiny_ckpt}", f"--tasks={TASKS}", "--suites=all", "--episodes=1",
            "--num_envs=2", f"--out={out}", f"--executable_store={tmp_path / 'store'}"]
    stdout = _run_main([*argv, "--compile_only"])  # compiles what the run would, runs and writes nothing
    assert "2 episodes pending, 2 envs: compiled in" in stdout and not out.exists()
    _run_main(argv)
    res = json.loads(out.read_text())
    assert res["settings"]["method"] == "ar" and res["settings"]["tasks"] == TASKS.split(",")
    # what ran: the checkpoint's dtype, attention resolved from auto (XLA's off a GPU)
    assert res["numerics"] == {"dtype": "float32", "matmul_precision": "float32", "unroll": False,
                               "attention": "xla", "patchify": "conv"}
    split = res["timing"]["compile_split"]  # the program --compile_only compiled, loaded from the store
    assert set(split) == {"trace", "lower", "xla", "store"} and split["trace"] == split["xla"] == 0.0
    assert sum(split.values()) == pytest.approx(res["timing"]["compile_seconds"], rel=1e-6)
    host = res["timing"]["host_split"]
    assert set(host) == {"start", "setup", "other"} and sum(host.values()) == pytest.approx(
        res["timing"]["host_seconds"], rel=1e-6)
    for task in TASKS.split(","):
        (ep,) = res["episodes"][task]
        assert isinstance(ep["success"], bool) and ep["steps"] > 0
        # AR: one prefill + 6 cached passes for every action taken, 7 tokens each; no invalid rows.
        assert ep["decode"] == {"target_passes": 7.0 * ep["steps"], "tokens": 7.0 * ep["steps"], "invalid": 0.0}
    for suite in ("spatial", "object"):
        s = res["summary"]["suites"][suite]
        assert s["episodes"] == 1 and 0.0 <= s["success_rate"] <= 1.0
        assert s["target_passes_per_action"] == 7.0 and s["tokens_per_target_pass"] == 1.0
    assert res["timing"]["control_steps"] > 0 and res["timing"]["ms_per_control_step"] > 0
    before = out.read_text()
    stdout = _run_main(argv)  # same settings: nothing left to run, the file keeps its episodes
    assert "0 to run" in stdout
    again = json.loads(out.read_text())
    assert again["episodes"] == json.loads(before)["episodes"]
    # ... and the speed of the run it resumed, summed with its own (which ran nothing)
    (first,) = again["timing"]["earlier"]
    assert first["control_steps"] == res["timing"]["control_steps"] and again["timing"]["control_steps"] == 0
    assert again["timing"]["all_runs"]["runs"] == 2 and again["timing"]["all_runs"]["ms_per_control_step"] == (
        pytest.approx(res["timing"]["ms_per_control_step"]))


def test_shipped_checkpoint_loads_in_one_call_and_fits_the_size_limits():
    params, cfg, tok, meta = checkpoint.load_policy(vla_policy.DEFAULT_CHECKPOINT)
    n = sum(x.size for x in jax.tree.leaves(params))
    assert 5e6 <= n <= 10e6 and cfg.n_layers >= 8 and cfg.image_size == 64
    assert all(lo < hi for lo, hi in zip(tok.q01, tok.q99))
    files = [f for f in vla_policy.DEFAULT_CHECKPOINT.parent.rglob("*") if f.is_file()]
    assert max(f.stat().st_size for f in files) <= 16 << 20
    assert sum(f.stat().st_size for f in files) < 48 << 20


def test_ar_policy_acts_on_a_batch_like_ar_decode(tiny_ckpt, compiled):
    """The policy's action equals detokenized ar_decode of the same observations."""
    params, cfg, tok, _ = checkpoint.load_policy(tiny_ckpt)
    pol = vla_policy.decoding_policy("ar", params, cfg, tok, vla_policy.ar)
    state = compiled.start([0, 11])
    state = state.replace(obs=state.obs.replace(image=jax.random.randint(
        jax.random.PRNGKey(0), (2, 64, 64, 3), 0, 255).astype(np.uint8)))
    action, _, stats = pol.act(pol.params, state, (), None)
    tokens, _ = target_model.ar_decode(params, cfg, vla_policy.observation(state))
    np.testing.assert_allclose(np.asarray(action), np.asarray(tok.to_actions(tokens)), rtol=1e-6)
    assert action.shape == (2, 7) and np.all(np.asarray(stats["target_passes"]) == 7)


def test_shipped_drafter_policy_in_strict_mode_acts_like_ar(compiled):
    """The registered `drafter` method loads the shipped target + drafter pair and, with
    strict acceptance, emits the AR policy's actions."""
    cam = methods.env_config("drafter").camera  # the views the shipped target was trained on
    env = TabletopEnv(config=EnvConfig(camera=cam, render=False))
    spec_pol = methods.make_policy("drafter", env, top_k=4, depth=3, total_tokens=12)
    ar_pol = methods.make_policy("ar", env)
    state = compiled.start([0, 11])
    state = state.replace(obs=state.obs.replace(image=jax.random.randint(
        jax.random.PRNGKey(1), (2, *cam.image_shape), 0, 255).astype(np.uint8)))
    a_spec, _, stats = jax.jit(spec_pol.act)(spec_pol.params, state, (), None)
    a_ar, _, _ = jax.jit(ar_pol.act)(ar_pol.params, state, (), None)
    np.testing.assert_array_equal(np.asarray(a_spec), np.asarray(a_ar))
    assert np.all(np.asarray(stats["target_passes"]) <= 7) and np.all(np.asarray(stats["drafter_passes"]) >= 1)


def test_eval_config_rejects_out_of_range_settings():
    with pytest.raises(ValueError, match="episodes_per_task must be in 1..50, got 0"):
        ev.EvalConfig(episodes_per_task=0)
    with pytest.raises(ValueError, match="episodes_per_task must be in 1..50, got 51"):
        ev.EvalConfig(episodes_per_task=51)
    with pytest.raises(ValueError, match="num_envs must be >= 1, got 0"):
        ev.EvalConfig(num_envs=0)
    with pytest.raises(ValueError, match="tail_envs must be 0 \\(off\\) or in 1..7"):
        ev.EvalConfig(num_envs=8, tail_envs=8)
    with pytest.raises(ValueError, match="tail_envs needs refill"):
        ev.EvalConfig(num_envs=8, tail_envs=2, refill=False)


def test_an_interrupted_run_resumes_with_exactly_its_missing_episodes(compiled):
    """What a resumed run does: the episodes recorded as None, missing from a task's list, or
    of a task not yet started; nothing that is recorded."""
    env = compiled.env
    names = [t.name for t in env.tasks]
    cfg = ev.EvalConfig(episodes_per_task=3, num_envs=2)
    rec = {"success": True, "steps": 5, "failure": None}
    done = {names[0]: [rec, None, rec], names[1]: [rec], **{n: [rec] * 3 for n in names[3:]}}
    assert ev.pending_episodes(env, cfg, done) == [(0, 1), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2)]
    assert len(ev.pending_episodes(env, cfg, {})) == 3 * len(names)
    everything = {n: [rec] * 3 for n in names}  # nothing pending: nothing to compile
    assert ev.compile_rollout(env, None, cfg, everything) == {}


def test_evaluate_refuses_a_results_file_of_other_settings_and_keeps_it(tmp_path):
    """Refused before anything is built (the entry point, in its own process)."""
    out = tmp_path / "eval.json"
    results_io.write_json_atomic(out, {"settings": {"method": "ar", "tasks": ["left_block_plate"]},
                                       "episodes": {"left_block_plate": [{"success": True}]}})
    before = out.read_text()
    r = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--method=expert", "--tasks=left_block_plate",
                        "--episodes=1", "--num_envs=1", f"--out={out}"], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert r.returncode != 0 and "other settings" in r.stderr, r.stderr[-3000:]
    assert out.read_text() == before
    # The physics is part of the settings: results under MJX's rule are not resumed under C's.
    results_io.write_json_atomic(out, {"settings": {"method": "expert", "tasks": ["left_block_plate"],
                                                    "episodes_per_task": 1},
                                       "episodes": {"left_block_plate": [{"success": True}]}})
    before = out.read_text()
    r = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--method=expert", "--tasks=left_block_plate",
                        "--episodes=1", "--num_envs=1", "--physics=clamp_aware_implicit=true", f"--out={out}"],
                       capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert r.returncode != 0 and "other settings" in r.stderr, r.stderr[-3000:]
    assert out.read_text() == before


def test_evaluate_resumes_only_over_the_same_checkpoint_files_and_method_config(tmp_path):
    """A results file records what its checkpoint held, not only its path, and every setting
    its method ran with, not only those given: a target installed at the same path since, or a
    method default changed since, is refused (its episodes would be another target's or
    another config's), the same files and config resume it (every episode done: nothing runs)."""
    from envs import physics
    from experiments import cli
    from heisd_jax.harness import executable_store

    shipped = executable_store.file_digest(vla_policy.DEFAULT_CHECKPOINT)[:16]

    def settings(digest, config=cli.config_digest("ar", {})):
        return {"method": "ar", "tasks": ["left_block_plate"], "episodes_per_task": 1,
                "checkpoint": os.path.abspath(vla_policy.DEFAULT_CHECKPOINT), "config": config,
                "physics": dataclasses.asdict(physics.parse("")), "contents": {"checkpoint": digest}}

    def run(out):
        return subprocess.run([sys.executable, "-m", "experiments.evaluate", "--method=ar", "--tasks=left_block_plate",
                               "--episodes=1", "--num_envs=1", f"--out={out}"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parents[1], timeout=300)

    done = {"left_block_plate": [{"success": True, "steps": 50, "failure": None}]}
    for name, recorded in (("other_files", settings("0" * 16)), ("other_default", settings(shipped, "0" * 16))):
        other = tmp_path / f"{name}.json"
        results_io.write_json_atomic(other, {"settings": recorded, "episodes": done})
        before = other.read_text()
        r = run(other)
        assert r.returncode != 0 and "other settings" in r.stderr, (name, r.stderr[-3000:])
        assert other.read_text() == before
    same = tmp_path / "same.json"
    results_io.write_json_atomic(same, {"settings": settings(shipped), "episodes": done})
    r = run(same)
    assert r.returncode == 0 and "1 tasks x 1 episodes, 0 to run" in r.stdout, r.stderr[-3000:]


def test_summary_counts_per_action_and_per_episode():
    """A method that takes more steps per episode pays per episode even at fewer passes per action."""
    task = tasks_lib.get_tasks("spatial")[0]
    results = {task.name: [{"success": True, "steps": 10, "decode": {"target_passes": 30.0, "tokens": 70.0}},
                           {"success": False, "steps": 30, "decode": {"target_passes": 60.0, "tokens": 210.0}}]}
    summary = ev.summarize((task,), results)
    s = summary["suites"]["spatial"]
    assert s["episodes"] == 2 and s["success_rate"] == 0.5 and s["mean_steps"] == 20.0
    assert s["target_passes_per_action"] == 90.0 / 40 and s["target_passes_per_episode"] == 45.0
    assert s["tokens_per_target_pass"] == 280.0 / 90
    assert summary["tasks"][task.name]["target_passes_per_episode"] == 45.0


def test_suites_of_one_env_share_one_compiled_rollout():
    """Task ids and the seed are data: an env over two suites' tasks evaluates each suite
    (`tasks`), under any seed, with one program (3 episodes in 2 slots: a queue, with its
    starts' program), compiled for the first call and reused, untraced, by the second."""
    env = TabletopEnv(tasks_lib.get_tasks("spatial,object", ["left_block_plate", "pick_red_block"]),
                      EnvConfig(render=False))
    policy = methods.make_policy("expert", env)
    cfg = ev.EvalConfig(episodes_per_task=3, num_envs=2)
    rollouts, timings = {}, []
    parts = [ev.evaluate(env, policy, cfg, tasks={name}, seed=seed, rollouts=rollouts,
                         on_batch=lambda r, t: timings.append(t))
             for name, seed in (("left_block_plate", 0), ("pick_red_block", 3))]  # the seed is an input too
    assert [list(p) for p in parts] == [["left_block_plate"], ["pick_red_block"]]
    assert len(rollouts) == 1 and timings[0]["compile_seconds"] > 0 and timings[1]["compile_seconds"] == 0.0
    assert all(len(p[name]) == 3 and all(r is not None for r in p[name]) for p in parts for name in p)


def test_a_seed_given_as_data_folds_the_keys_as_a_static_one():
    from envs import rollout

    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    as_data = jax.jit(rollout.seeded_keys)
    for seed in (0, 1, 7):
        np.testing.assert_array_equal(as_data(keys, np.int32(seed)), rollout.seeded_keys(keys, seed))
    np.testing.assert_array_equal(rollout.seeded_keys(keys, 0), keys)  # seed 0: the historical keys


@pytest.fixture(scope="module")
def expert_queue():
    """The expert on one task, 3 episodes in 2 slots (a queue), and the compiled rollouts the
    tests below share: (env, policy, config, rollouts)."""
    env = TabletopEnv(tasks_lib.get_tasks("spatial", ["left_block_plate"]), EnvConfig(render=False))
    return env, methods.make_policy("expert", env), ev.EvalConfig(episodes_per_task=3, num_envs=2), {}


def test_a_deterministic_rollout_is_a_program_of_its_own_that_plays_the_same_episodes(expert_queue):
    """`EvalConfig.deterministic` compiles the rollout with `xla_options.DETERMINISTIC` (a GPU's
    atomics made deterministic; a CPU is so already, so the episodes are the same here), as a
    program of its own: a caller's compiled rollouts keep both apart."""
    env, policy, cfg, rollouts = expert_queue
    plain = ev.evaluate(env, policy, cfg, rollouts=rollouts)
    programs = len(rollouts)
    det = ev.evaluate(env, policy, dataclasses.replace(cfg, deterministic=True), rollouts=rollouts)
    assert plain == det and len(plain["left_block_plate"]) == 3 and len(rollouts) == programs + 1


class _LeaseEnded(Exception):
    pass


def test_a_queue_saves_its_ended_episodes_and_a_resumed_run_ends_as_one_run(expert_queue):
    """Within a refilled call, `on_progress` gets the episodes that have ended (none of them
    before it ends); a run stopped after such a save (a lease that ends) and resumed from what
    it saved gives the results of one uninterrupted run."""
    env, policy, cfg, rollouts = expert_queue
    cfg = dataclasses.replace(cfg, save_every_s=1e-9)  # a save every round
    whole = ev.evaluate(env, policy, dataclasses.replace(cfg, save_every_s=0.0), rollouts=rollouts)
    saves = []

    def on_progress(results, timing):
        saves.append(json.loads(json.dumps(results)))  # a copy, as a results file holds it
        shares.append(timing)
        raise _LeaseEnded

    shares = []

    with pytest.raises(_LeaseEnded):
        ev.evaluate(env, policy, cfg, rollouts=rollouts, on_progress=on_progress)
    (saved,) = saves
    ended = [r for r in saved["left_block_plate"] if r is not None]
    assert 0 < len(ended) < 3 and all(r in whole["left_block_plate"] for r in ended)
    (share,) = shares  # the running call's speed so far, with the episodes saved
    assert share["control_steps"] > 0 and share["episodes"] == len(ended) and share["batch_seconds"] > 0
    assert ev.evaluate(env, policy, cfg, done=saved, rollouts=rollouts) == whole
    with pytest.raises(ValueError, match="save_every_s must be >= 0"):
        ev.EvalConfig(save_every_s=-1.0)

    # `stop` (a signal's flag) ends the queue after a round, its ended episodes handed over
    # first, with no periodic save at all; the resumed run again ends as one run.
    asked, calls = [], []
    ev.evaluate(env, policy, cfg, rollouts=rollouts, stop=lambda: asked.append(1) or False,
                on_batch=lambda r, t: calls.append(t))
    rounds = len(asked)  # `stop` is asked before the call and after each round
    cfg0, saves = dataclasses.replace(cfg, save_every_s=0.0), []
    with pytest.raises(ev.EvaluationStopped) as stopped:
        ev.evaluate(env, policy, cfg0, rollouts=rollouts, on_progress=lambda r, t: saves.append(json.loads(json.dumps(r))),
                    stop=lambda: (asked.append(1) or len(asked) - rounds > 0.8 * rounds))
    (saved,) = saves
    ended = [r for r in saved["left_block_plate"] if r is not None]
    assert 0 < len(ended) < 3 and all(r in whole["left_block_plate"] for r in ended)
    assert stopped.value.results == saved
    # ... with the stopped call's speed: the rounds it ran, its ended episodes, and the env
    # steps of those and of the running ones
    (call,), part = calls, stopped.value.timing
    assert 0 < part["control_steps"] < call["control_steps"] and part["episodes"] == len(ended)
    assert sum(r["steps"] for r in ended) < part["env_steps"] < call["env_steps"]
    assert part["batch_seconds"] > 0 and part["devices"] == call["devices"]
    assert ev.evaluate(env, policy, cfg0, done=saved, rollouts=rollouts) == whole
    with pytest.raises(ev.EvaluationStopped) as stopped:  # asked before a call: nothing runs
        ev.evaluate(env, policy, cfg0, rollouts=rollouts, stop=lambda: True)
    assert stopped.value.timing is None
