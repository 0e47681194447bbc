"""Scripted experts in the batched evaluator: they solve sampled initial states of every suite;
`rollout.host_loop` steps their episodes as `run_episodes` does."""

import numpy as np
import pytest

from envs import expert, tasks
from envs.env import EnvConfig, TabletopEnv
from heisd_jax.harness import evaluator as ev, methods

# Two tasks per suite, covering every goal kind (place on plate / in basket / in zone, push,
# stack, lift, two-stage).
SAMPLE = ["left_block_plate", "near_plate_cylinder_basket", "pick_purple_block", "pick_green_cylinder",
          "push_red_block_zone", "stack_green_on_red", "lift_blue_cylinder", "stack_red_on_blue_green_cylinder_basket"]


@pytest.fixture(scope="module")
def expert_results():
    task_list = tasks.get_tasks("all", SAMPLE)
    env = TabletopEnv(task_list, EnvConfig(render=False))
    cfg = ev.EvalConfig(episodes_per_task=1, num_envs=len(task_list))
    seen = []
    results = ev.evaluate(env, methods.make_policy("expert", env), cfg, on_batch=lambda r, t: seen.append(t))
    return env, results, seen


@pytest.mark.slow  # `expert_results` runs 8 tasks to the end under the expert
def test_expert_solves_sampled_initial_states_of_every_suite(expert_results):
    env, results, _ = expert_results
    assert {t.suite for t in env.tasks} == set(tasks.SUITES)
    failed = {name: recs for name, recs in results.items() if not recs[0]["success"]}
    assert not failed, failed


@pytest.mark.slow
def test_evaluator_reports_every_episode_once(expert_results):
    env, results, seen = expert_results
    assert len(seen) == 1 and seen[0]["episodes"] == len(SAMPLE)
    assert sorted(results) == sorted(SAMPLE)
    summary = ev.summarize(env.tasks, results)
    assert sum(s["episodes"] for s in summary["suites"].values()) == len(SAMPLE)
    assert all(r[0]["steps"] < t.max_steps for t in env.tasks for r in [results[t.name]])
    # Nothing is pending any more, so a resumed run does no work.
    assert ev.pending_episodes(env, ev.EvalConfig(episodes_per_task=1, num_envs=4), results) == []


def test_unknown_method_lists_valid_methods():
    with pytest.raises(ValueError, match="valid methods: .*ar.*expert"):
        methods.make_policy("greedy", None)


def test_expert_phase_names_name_each_phase_constant():
    """PHASE_NAMES[phase] is the phase constant's own name (failure analyses print them)."""
    phases = {n: getattr(expert, n.upper()) for n in expert.PHASE_NAMES}
    assert sorted(phases.values()) == list(range(len(expert.PHASE_NAMES)))  # one name per phase, no gap
    assert all(expert.PHASE_NAMES[v] == n for n, v in phases.items())


@pytest.mark.slow  # two compiles of the expert's control step
def test_host_loop_steps_the_episodes_run_episodes_runs():
    import jax  # noqa: PLC0415
    from envs import rollout  # noqa: PLC0415

    env = TabletopEnv(tasks.get_tasks("spatial", ["left_block_plate"]), EnvConfig(render=False))
    tids, keys = env.cycling_eval_starts(2)
    want, _, _ = jax.jit(lambda k, t: rollout.run_episodes(env, expert.policy(env), k, t, 3))(keys, tids)
    states = rollout.host_loop(env, expert.policy(env), keys, tids)
    got = [next(states) for _ in range(4)][-1]
    np.testing.assert_array_equal(np.asarray(got.step), [3, 3])
    np.testing.assert_allclose(np.asarray(got.data.qpos), np.asarray(want.data.qpos), rtol=0, atol=1e-6)


def test_rotation_gain_scales_the_rotation_command_alone():
    """`ExpertConfig.rot_gain` scales the rotation part of the expert's action (where neither
    saturates) and leaves translation and the jaw as they are."""
    import jax  # noqa: PLC0415

    env = TabletopEnv(tasks.get_tasks("spatial", ["left_block_plate"]), EnvConfig(render=False))
    tids, keys = env.cycling_eval_starts(1)
    state = jax.tree.map(lambda x: x[0], jax.vmap(env.reset)(keys, tids))

    def action(rot_gain):
        cfg = expert.ExpertConfig(rot_gain=rot_gain)
        return np.asarray(expert.act(env, state, expert.init(state, env), jax.random.PRNGKey(0), cfg)[0])

    small, double = action(0.01), action(0.02)
    np.testing.assert_array_equal(small[:3], double[:3])
    np.testing.assert_array_equal(small[6], double[6])
    assert np.abs(small[3:6]).max() > 1e-4
    np.testing.assert_allclose(double[3:6], 2 * small[3:6], rtol=1e-5, atol=1e-7)
