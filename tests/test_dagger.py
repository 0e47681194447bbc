"""DAgger collection: the teacher labels the states the policy visits; beta mixes who acts;
the entry points that collect and build refuse bad settings before they start."""

import gzip
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import flagsaver

from envs import expert, rollout
from envs.env import EnvConfig, TabletopEnv

N_STEPS = 12
TASKS = np.array([0, 25], np.int32)


def _still(env):
    """A learner that never moves (and keeps the jaw open)."""
    return rollout.per_env("still", lambda s: jnp.zeros(()),
                           lambda s, p, k: (jnp.zeros(7).at[6].set(-1.0), p))


@pytest.fixture(scope="module")
def runs():
    env = TabletopEnv(config=EnvConfig(render=False))
    teacher, learner = expert.policy(env), _still(env)
    keys = env.initial_state_keys(TASKS, [0, 1], split="train")
    dagger = jax.jit(lambda beta: rollout.record_episodes(env, learner, keys, TASKS, N_STEPS, teacher=teacher,
                                                          beta=beta)[1])
    plain = jax.jit(lambda: rollout.record_episodes(env, teacher, keys, TASKS, N_STEPS)[1])
    # The teacher's own rollout again, as one program with a traced time limit runs it: the
    # first N_STEPS of 4 more rows.
    limited = jax.jit(lambda limit: rollout.record_episodes(env, teacher, keys, TASKS, N_STEPS + 4, limit=limit))
    return dagger(1.0), dagger(0.0), plain(), limited(jnp.int32(N_STEPS))


@pytest.mark.slow  # the `runs` fixture compiles three expert/learner rollouts: ~3 min on 2 cores
def test_beta_one_is_the_teachers_own_rollout(runs):
    at_one, _, own, _ = runs
    for field in ("proprio", "action", "ee_vel"):  # two programs: equal up to float rounding
        np.testing.assert_allclose(at_one[field], own[field], atol=1e-4)
    np.testing.assert_array_equal(at_one["policy_action"][..., 6], -1.0)  # the learner's own, recorded beside


@pytest.mark.slow
def test_beta_zero_labels_the_learners_states(runs):
    _, at_zero, own, _ = runs
    # The arm does not move under the still learner (only the servos settle) ...
    drift = np.abs(at_zero["proprio"][-1, :, :3] - at_zero["proprio"][0, :, :3]).max()
    assert drift < 0.01, drift
    # ... while the labels are the expert's commands to move, away from the expert's own states.
    assert np.abs(at_zero["action"][:, :, :3]).max() > 0.5
    assert np.abs(own["proprio"][-1, :, :3] - at_zero["proprio"][-1, :, :3]).max() > 0.02


@pytest.mark.slow
def test_a_traced_time_limit_runs_the_same_steps_and_leaves_the_rest_zero(runs):
    _, _, own, (final, limited) = runs
    np.testing.assert_array_equal(np.asarray(final.step), [N_STEPS, N_STEPS])  # stopped at the limit
    for field in ("proprio", "action", "ee_vel"):
        np.testing.assert_allclose(limited[field][:N_STEPS], own[field], atol=1e-4)  # two programs: rounding
        assert not np.any(limited[field][N_STEPS:])


def test_collect_demos_rejects_beta_without_policy(tmp_path):
    from absl import app, flags

    from experiments import collect_demos

    flags.FLAGS.mark_as_parsed()
    with flagsaver.flagsaver(beta=0.5, out=str(tmp_path / "d")), pytest.raises(app.UsageError, match="--policy"):
        collect_demos.main([])
    policy = str(tmp_path)  # an existing directory (the flag's validator refuses a missing one)
    with flagsaver.flagsaver(beta=1.5, policy=policy, out=str(tmp_path / "d")), pytest.raises(app.UsageError,
                                                                                             match=r"\[0, 1\]"):
        collect_demos.main([])
    assert not (tmp_path / "d").exists()


def test_build_target_refuses_a_work_dir_built_with_other_settings(tmp_path):
    """A rerun resumes only the build its settings describe: other settings are refused
    before any stage runs, and the record of the earlier build is kept."""
    state = tmp_path / "build.json"
    state.write_text(json.dumps({"settings": {"rounds": 7}, "stages": {"demos": {"seconds": 1.0}}}))
    before = state.read_text()
    r = subprocess.run([sys.executable, "-m", "experiments.build_target", f"--work={tmp_path}", "--rounds=1"],
                       capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert r.returncode != 0 and "built with other settings" in r.stderr and "use another --work" in r.stderr, \
        r.stderr[-3000:]
    assert state.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["build.json", "logs"]  # no stage started


def test_build_target_resumed_elsewhere_runs_only_what_follows_what_came_back(tmp_path):
    """A build resumed from what a lost machine's last poll brings back (the newest policy and
    the evaluation, no dataset) reruns a stage whose output is gone only where a stage still to
    run reads it: with the fresh round and no drafter, nothing before the fresh round; with the
    drafter, which reads every dataset, every collection and the policies that drove them."""
    root = Path(__file__).resolve().parents[1]
    w = tmp_path / "w"
    (w / "vla2" / "0").mkdir(parents=True)
    (w / "eval_ar.json").write_text(json.dumps({"episodes": {"pick_red_block": [{}], "left_block_plate": [{}]}}))
    base = [sys.executable, "-m", "experiments.build_target", f"--work={w}", "--dry_run", "--rounds=2",
            "--tasks=pick_red_block,left_block_plate", "--eval_episodes=1"]

    def statuses(*flags):
        r = subprocess.run([*base, *flags], capture_output=True, text=True, cwd=root, timeout=300)  # the last --work counts
        assert r.returncode == 0, r.stderr[-3000:]
        return {line.split()[0]: line.split(" (", 1)[1].split(")")[0].split(":")[0]
                for line in r.stdout.splitlines() if ": python -m " in line}

    got = statuses("--fresh_round", "--fresh_weight=0", "--skip=drafter,datastore,calibration")
    assert got == {**dict.fromkeys(["demos", "train0", "dagger1", "train1", "dagger2"], "not needed"),
                   "train2": "done", "eval": "done",
                   **dict.fromkeys(["fresh_demos", "dagger3", "train3", "fresh_eval"], "to run")}, got
    # By default the fresh round trains on the aggregate too, so the aggregate is collected again.
    got = statuses("--fresh_round", "--skip=drafter,datastore,calibration")
    assert got == {**dict.fromkeys(["demos", "train0", "dagger1", "train1", "dagger2"], "to run"),
                   "train2": "done", "eval": "done",
                   **dict.fromkeys(["fresh_demos", "dagger3", "train3", "fresh_eval"], "to run")}, got
    got = statuses("--skip=datastore,calibration")
    assert got == {**dict.fromkeys(["demos", "train0", "dagger1", "train1", "dagger2"], "to run"),
                   "train2": "done", "eval": "done", "target_rollouts": "to run", "drafter": "to run"}, got
    # Continuing a policy with the fresh round alone: no stage reads the demonstrations, so none are collected.
    got = statuses(f"--work={tmp_path / 'c'}", f"--start={w / 'vla2'}", "--steps=0", "--rounds=0", "--fresh_round",
                   "--fresh_weight=0", "--skip=drafter,datastore,calibration")
    assert got == {"demos": "not needed", "eval": "to run",
                   **dict.fromkeys(["fresh_demos", "dagger1", "train1", "fresh_eval"], "to run")}, got
    r = subprocess.run([*base, "--fresh_round", "--skip=eval"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode != 0 and "--fresh_round weighs its collections by the evaluation's failures" in r.stderr


def test_build_target_refuses_a_batch_its_devices_cannot_split(tmp_path):
    """By default every training stage runs data parallel over all local devices (here two
    forced CPU devices): a minibatch they cannot split evenly is refused before any stage runs."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=2")
    r = subprocess.run([sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}", "--batch_size=255"],
                       capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300, env=env)
    assert r.returncode != 0 and "must be a multiple of the 2 devices" in r.stderr, r.stderr[-3000:]
    assert not (tmp_path / "w").exists()


def test_build_target_stages_pass_only_flags_their_commands_define(tmp_path):
    """Every stage of a build with every option set runs a command that knows each flag it is
    given (a flag meant for one stage, e.g. --suite_weights for the collections, must not reach
    another), checked against each command's own flag definitions before any GPU time is spent."""
    root = Path(__file__).resolve().parents[1]
    start = tmp_path / "start"
    (start / "0").mkdir(parents=True)
    r = subprocess.run([sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}", "--dry_run",
                        f"--start={start}", "--steps=0", "--rounds=2", "--beta=0.5,0", "--suite_weights=long:2",
                        "--tasks=pick_red_block,left_block_plate", "--label_sigma_bins=1",
                        "--rollout_episodes=10", "--datastore_source=rollouts", "--adapt_weights", "--nodeterministic",
                        "--fresh_round"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    stages = [line.split(": python -m experiments.", 1) for line in r.stdout.splitlines() if ": python -m " in line]
    assert [s.split()[0] for s, _ in stages] == ["demos", "dagger1", "train1", "dagger2", "train2", "eval",
                                                 "fresh_demos", "dagger3", "train3", "fresh_eval",
                                                 "target_rollouts", "drafter", "datastore", "calibration"]
    assert not (tmp_path / "w").exists()  # a dry run writes nothing
    by_module = {}
    for _, cmd in stages:
        module, *args = cmd.split()
        by_module.setdefault(module, set()).update(a[2:].split("=")[0] for a in args)
    list_flags = "import sys, importlib; from absl import flags; importlib.import_module(sys.argv[1]); print(*flags.FLAGS)"
    procs = {m: subprocess.Popen([sys.executable, "-c", list_flags, f"experiments.{m}"], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, cwd=root) for m in by_module}
    for module, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-3000:]
        unknown = by_module[module] - set(out.split())
        assert not unknown, f"experiments.{module} does not define {sorted(unknown)}"
    assert "suite_weights" in by_module["collect_demos"] and "suite_weights" not in by_module["evaluate"]
    rounds = {s.split()[0]: cmd for s, cmd in stages}
    assert "--weights_from" not in rounds["dagger1"]  # no earlier round to weigh by
    assert f"--weights_from={tmp_path / 'w' / 'dagger1'} --keep_total" in rounds["dagger2"]  # the previous round's failures
    # Fine-tuning is drawn by the failures of the policy it fine-tunes, where that policy drove alone (beta 0).
    assert "--weights_from" not in rounds["train1"] and f"--weights_from={tmp_path / 'w' / 'dagger2'}" in rounds["train2"]
    # every training and collection stage
    # The fresh round: the last policy drives alone, both collections weighed by the evaluation; trained on the
    # aggregate with the fresh data drawn --fresh_weight (default 4) times as often.
    w = tmp_path / "w"
    for name in ("fresh_demos", "dagger3"):
        assert f"--weights_from={w / 'eval_ar.json'} --keep_total" in rounds[name], rounds[name]
    assert f"--policy={w / 'vla2'} --beta=0.0" in rounds["dagger3"]
    aggregate = ",".join(str(w / d) for d in ("demos", "dagger1", "dagger2", "fresh_demos", "dagger3"))
    assert f"--demos={aggregate} " in rounds["train3"] and "--demo_weights=1,1,1,4,4 " in rounds["train3"]
    assert "--weights_from" not in rounds["train3"]
    assert f"--checkpoint={w / 'vla3'}" in rounds["fresh_eval"] and f"--out={w / 'eval_ar_fresh.json'}" in rounds["fresh_eval"]
    assert all(f"--checkpoint={w / 'vla3'}" in rounds[s] for s in ("datastore", "calibration"))
    assert f"--target={w / 'vla3'}" in rounds["drafter"] and f"--policy={w / 'vla3'}" in rounds["target_rollouts"]
    assert all("--deterministic=false" in rounds[s] for s in ("demos", "dagger1", "train1", "dagger2", "train2",
                                                              "fresh_demos", "dagger3", "train3",
                                                              "target_rollouts", "drafter"))
    assert "--deterministic" not in rounds["eval"]  # evaluate's default is off (and --deterministic turns it on)


def test_failure_weights_follow_the_failure_rate():
    from envs import tasks

    rates = {"far_plate_block_basket": 0.60, "near_plate_cylinder_basket": 0.82, "push_green_block_zone": 0.86,
             "left_block_plate": 0.96, "pick_red_block": 1.0}
    # 1 + round(10 x failure rate), capped at 4; tasks that would get 1x are left out.
    assert tasks.failure_weights(rates) == ["far_plate_block_basket:4", "near_plate_cylinder_basket:3",
                                            "push_green_block_zone:2"]
    assert tasks.failure_weights(rates, max_weight=2)[0] == "far_plate_block_basket:2"
    assert tasks.parse_suite_weights(tasks.failure_weights(rates))  # valid weights
    for bad in ({"nope": 0.5}, {"pick_red_block": 1.5}):
        with pytest.raises(ValueError, match="bad task success rate"):
            tasks.failure_weights(bad)


def test_episode_counts_share_out_a_kept_total_by_weight():
    from envs import tasks

    chosen = tasks.get_tasks("all", ["far_plate_block_basket", "left_block_plate", "pick_red_block", "red_block_plate"])
    suites = tasks.parse_suite_weights(["spatial:2"])
    assert tasks.episode_counts(chosen, 25, suites) == {"far_plate_block_basket": 50, "left_block_plate": 50,
                                                        "pick_red_block": 25, "red_block_plate": 25}
    failures = tasks.parse_suite_weights(["far_plate_block_basket:4", "pick_red_block:3", "spatial:2"])
    grown = tasks.episode_counts(chosen, 25, failures)
    assert grown == {"far_plate_block_basket": 100, "left_block_plate": 50, "pick_red_block": 75, "red_block_plate": 25}
    for total in (150, 151, 4, 997):
        kept = tasks.episode_counts(chosen, 25, failures, total)
        assert sum(kept.values()) == total and min(kept.values()) >= 1
        # shared out in the weights' order, each within one episode of its exact share
        assert kept["far_plate_block_basket"] >= kept["pick_red_block"] >= kept["left_block_plate"] >= kept["red_block_plate"]
        exact = {name: 1 + (total - 4) * n / sum(grown.values()) for name, n in grown.items()}
        assert all(abs(kept[name] - exact[name]) < 1 for name in kept), (total, kept)
    assert tasks.episode_counts(chosen, 25, suites, 150) == tasks.episode_counts(chosen, 25, suites)  # no change
    with pytest.raises(ValueError, match="3 episodes cannot give each of 4 tasks one"):
        tasks.episode_counts(chosen, 25, failures, 3)


def test_shared_episode_counts_keep_each_time_limits_total():
    """Failure weights move episodes only between tasks of one time limit, so a round's
    batches (one per limit) keep their shapes whatever the policy failed."""
    from envs import tasks

    chosen = tasks.get_tasks("all", ["far_plate_block_basket", "pick_red_block", "red_green_blocks_basket",
                                     "both_cylinders_basket"])
    assert len({t.max_steps for t in chosen}) == 2  # two short tasks, two long ones
    given = tasks.parse_suite_weights(["spatial:2", "long:2"])
    failures = tasks.parse_suite_weights(["far_plate_block_basket:4", "both_cylinders_basket:3", "spatial:2", "long:2"])
    before, after = tasks.episode_counts(chosen, 25, given), tasks.shared_episode_counts(chosen, 25, given, failures)
    assert list(after) == [t.name for t in chosen]
    for limit in {t.max_steps for t in chosen}:
        names = [t.name for t in chosen if t.max_steps == limit]
        assert sum(after[n] for n in names) == sum(before[n] for n in names)
    assert after["far_plate_block_basket"] > before["far_plate_block_basket"]
    assert after["both_cylinders_basket"] > after["red_green_blocks_basket"]
    assert tasks.shared_episode_counts(chosen, 25, given, given) == before  # no failures: no change

    from experiments.collect_demos import horizon_batches

    def shapes(counts):  # each batch's time limit and size: what the compiled program depends on
        pairs = [(t, e) for t, task in enumerate(chosen) for e in range(counts[task.name])]
        return [(limit, size) for limit, size, _ in horizon_batches(pairs, [t.max_steps for t in chosen], 100, 2)]

    assert shapes(after) == shapes(before)
    assert shapes(tasks.episode_counts(chosen, 25, failures, sum(before.values()))) != shapes(before)  # one total


def test_build_target_weights_from_an_evaluation(tmp_path):
    """--weights_from turns an evaluation's per-task failures into the collections' weights;
    an explicit --suite_weights entry for a task keeps its own weight; a file that is no
    evaluation is refused before anything runs."""
    root = Path(__file__).resolve().parents[1]
    start = tmp_path / "start"
    (start / "0").mkdir(parents=True)
    ev = tmp_path / "eval.json"
    ev.write_text(json.dumps({"summary": {"tasks": {"left_block_plate": {"success_rate": 0.6},
                                                    "pick_red_block": {"success_rate": 0.9}}}}))
    base = [sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}", "--dry_run",
            f"--start={start}", "--steps=0", "--rounds=1", "--tasks=pick_red_block,left_block_plate"]
    r = subprocess.run(base + [f"--weights_from={ev}", "--suite_weights=pick_red_block:3"],
                       capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    dagger = next(line for line in r.stdout.splitlines() if line.startswith("dagger1"))
    assert "--suite_weights=left_block_plate:4,pick_red_block:2,pick_red_block:3" in dagger
    ev.write_text("{}")
    r = subprocess.run(base + [f"--weights_from={ev}"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode != 0 and "nor an evaluation's results JSON" in r.stderr, r.stderr[-3000:]


def test_failure_weights_from_a_dagger_dataset(tmp_path):
    """A DAgger collection's own episodes give the next round's weights (the success of the
    policy that drove them, per task); an expert dataset, which keeps successes only, is refused."""
    from envs import demos
    from experiments import cli

    def dataset(path, policy, outcomes):
        w = demos.DatasetWriter(path, {"policy": policy})
        records = [dict(task=task, start=i, length=1, success=ok) for i, (task, ok) in enumerate(outcomes)]
        w.add_shard({f: np.zeros((len(records), 1), np.float32) for f in demos.STEP_FIELDS}, records)
        return w.finalize()

    # left_block_plate: 1 of 3 succeeded (failure 2/3 -> 1 + 7, capped at 4); pick_red_block: 9 of 10 (-> 2).
    outcomes = [("left_block_plate", i == 0) for i in range(3)] + [("pick_red_block", i > 0) for i in range(10)]
    assert cli.failure_weights(str(dataset(tmp_path / "dagger", "runs/vla0", outcomes))) == [
        "left_block_plate:4", "pick_red_block:2"]
    with pytest.raises(ValueError, match="an expert dataset"):
        cli.failure_weights(str(dataset(tmp_path / "demos", "expert", outcomes)))


def test_failure_weights_from_an_evaluation_plain_or_gzipped(tmp_path):
    """An evaluation's results give the same weights whether the file is plain or gzipped (the
    results committed under experiments/results are .json.gz)."""
    from experiments import cli

    result = {"episodes": {}, "summary": {"tasks": {"left_block_plate": {"success_rate": 0.5},
                                                    "pick_red_block": {"success_rate": 1.0}}}}
    plain, packed = tmp_path / "eval.json", tmp_path / "eval.json.gz"
    plain.write_text(json.dumps(result))
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    assert cli.failure_weights(str(packed)) == cli.failure_weights(str(plain)) == ["left_block_plate:4"]


def test_build_target_label_smoothing_follows_its_schedule(tmp_path):
    """--label_sigma_bins gives one value per policy trained (the last repeats); a build that
    gives every policy one value records it as builds before the schedule did (one number, none
    at the old default of 2), so they still resume; a bad value is one line, before any stage."""
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}", "--dry_run",
                        "--rounds=2", "--label_sigma_bins=2,0.6"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    sigma = {line.split()[0]: line.split("--label_sigma_bins=")[1].split()[0]
             for line in r.stdout.splitlines() if "--label_sigma_bins=" in line}
    assert sigma == {"train0": "2", "train1": "0.6", "train2": "0.6"}, r.stdout
    settings = ("import json, sys; from absl import flags; from experiments import build_target as b\n"
                "for argv in sys.argv[1:]:\n"
                "    flags.FLAGS.unparse_flags(); flags.FLAGS(['x', *argv.split()])\n"
                "    print(json.dumps(b._settings().get('label_sigma_bins')))")
    r = subprocess.run([sys.executable, "-c", settings, "", "--label_sigma_bins=2", "--label_sigma_bins=2,0.6 --rounds=2"],
                       capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split() == ["[2.0,", "2.0,", "0.6,", "0.6,", "0.6,", "0.6,", "0.6]", "null", "[2.0,", "0.6,", "0.6]"]  # the default: 2,2,0.6 (6 rounds)
    r = subprocess.run([sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}",
                        "--label_sigma_bins=2,-1"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode != 0 and "--label_sigma_bins: each value must be >= 0, got 2,-1" in r.stderr, r.stderr[-3000:]
    assert not (tmp_path / "w").exists()


def test_build_target_records_the_fresh_rounds_draw_only_where_it_trains_on_the_aggregate():
    """build.json records fresh_weight only for a fresh round that trains on the aggregate: a
    build whose fresh round trained on its own data alone (recorded before the flag existed)
    resumes with --fresh_weight=0 and is refused under the default, which means other data."""
    settings = ("import json, sys; from absl import flags; from experiments import build_target as b\n"
                "for argv in sys.argv[1:]:\n"
                "    flags.FLAGS.unparse_flags(); flags.FLAGS(['x', *argv.split()])\n"
                "    s = b._settings(); print(json.dumps([s.get('fresh_round'), s.get('fresh_weight')]))")
    r = subprocess.run([sys.executable, "-c", settings, "--fresh_round", "--fresh_round --fresh_weight=0",
                        "--fresh_weight=3"], capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1],
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.splitlines() == ["[true, 4]", "[true, null]", "[null, null]"]


def test_build_target_evaluates_deterministically_unless_told_not_to(tmp_path):
    root = Path(__file__).resolve().parents[1]
    for flag, want in (("--deterministic", True), ("--nodeterministic", False)):
        r = subprocess.run([sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}", "--dry_run",
                            flag], capture_output=True, text=True, cwd=root, timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        evaluation = next(line for line in r.stdout.splitlines() if line.startswith("eval "))
        assert ("--deterministic" in evaluation.split()) == want, evaluation


def test_build_target_passes_the_expert_rotation_gain_to_every_collection(tmp_path):
    """--expert_rot_gain reaches the demonstrations, every DAgger round and the target's
    rollouts (the expert labels them all), no training stage, and the build's record; unset, no
    stage names it (the expert's own default); a bad value is one line, before any stage."""
    root = Path(__file__).resolve().parents[1]
    base = [sys.executable, "-m", "experiments.build_target", f"--work={tmp_path / 'w'}", "--dry_run", "--rounds=2"]
    r = subprocess.run([*base, "--expert_rot_gain=0.5"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    named = {line.split()[0] for line in r.stdout.splitlines() if "--expert_rot_gain=0.5" in line.split()}
    assert named == {"demos", "dagger1", "dagger2", "target_rollouts"}, r.stdout
    r = subprocess.run(base, capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0 and "--expert_rot_gain" not in r.stdout, r.stdout
    settings = ("from absl import flags; from experiments import build_target as b\n"
                "flags.FLAGS(['x', '--expert_rot_gain=0.5']); print(b._settings()['expert_rot_gain'])")
    r = subprocess.run([sys.executable, "-c", settings], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode == 0 and r.stdout.split() == ["0.5"], r.stderr[-3000:]
    r = subprocess.run([*base, "--expert_rot_gain=0"], capture_output=True, text=True, cwd=root, timeout=300)
    assert r.returncode != 0 and "--expert_rot_gain must be > 0, got 0.0" in r.stderr, r.stderr[-3000:]
    assert not (tmp_path / "w").exists()
