"""An episode's result does not depend on where it ran: the same episodes evaluated 3 and 4 at
a time land in other slots, other batches and beside other (and padding) episodes, and end
identically (success, step, failure)."""

import pytest

from envs import expert, tasks
from envs.env import EnvConfig, TabletopEnv
from heisd_jax import evaluate as ev

pytestmark = pytest.mark.slow  # two expert rollouts compiled (minutes on 2 CPU cores)

TASKS = ["left_block_plate", "pick_red_block"]
EPISODES = 3  # 6 episodes: batches of 3 (one task each) vs of 4 (mixed, then 2 + 2 padding)


@pytest.fixture(scope="module")
def runs():
    env = TabletopEnv(tasks.get_tasks("all", TASKS), EnvConfig(render=False))
    policy = expert.policy(env)
    out = {}
    for num_envs in (3, 4):
        timing = []
        results = ev.evaluate(env, policy, ev.EvalConfig(episodes_per_task=EPISODES, num_envs=num_envs),
                              on_batch=lambda r, t: timing.append(t))
        out[num_envs] = results, timing
    return out


def test_batches_differ(runs):
    assert [t["episodes"] for t in runs[3][1]] == [3, 3]
    assert [t["episodes"] for t in runs[4][1]] == [4, 2]


def test_episode_results_do_not_depend_on_slot_or_batch(runs):
    (a, _), (b, _) = runs[3], runs[4]
    assert sorted(a) == sorted(b) == sorted(TASKS)
    for task in TASKS:
        assert len(a[task]) == len(b[task]) == EPISODES
        assert all(ep["steps"] > 0 for ep in a[task])
        ends = lambda eps: [(ep["success"], ep["steps"], ep["failure"]) for ep in eps]  # noqa: E731
        assert ends(a[task]) == ends(b[task]), task
