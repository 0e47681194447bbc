"""An episode's result does not depend on where it ran: the same episodes evaluated 3 and 4 at
a time land in other slots, other batches and beside other (and padding) episodes, and end
identically (success, step, failure); so do they when 2 or 4 env slots each take the next
pending episode as theirs ends (`EvalConfig.refill`), starting at other control steps, and
when the last ones go on in a batch of 2 (`EvalConfig.tail_envs`)."""

import pytest

from envs import expert, tasks
from envs.env import EnvConfig, TabletopEnv
from heisd_jax.harness import evaluator as ev

pytestmark = pytest.mark.slow  # two expert rollouts compiled (minutes on 2 CPU cores)

TASKS = ["left_block_plate", "pick_red_block"]
EPISODES = 3  # 6 episodes: batches of 3 (one task each) vs of 4 (mixed, then 2 + 2 padding)


@pytest.fixture(scope="module")
def runs():
    env = TabletopEnv(tasks.get_tasks("all", TASKS), EnvConfig(render=False))
    policy = expert.policy(env)
    out = {}
    for num_envs, refill, tail in ((3, False, 0), (4, False, 0), (2, True, 0), (4, True, 0), (4, True, 2)):
        timing = []
        cfg = ev.EvalConfig(episodes_per_task=EPISODES, num_envs=num_envs, refill=refill, tail_envs=tail)
        results = ev.evaluate(env, policy, cfg, on_batch=lambda r, t: timing.append(t))
        out[num_envs, refill] = out[num_envs, refill, tail] = results, timing
    return out


def test_batches_differ(runs):
    assert [t["episodes"] for t in runs[3, False][1]] == [3, 3]
    assert [t["episodes"] for t in runs[4, False][1]] == [4, 2]
    assert [t["episodes"] for t in runs[2, True][1]] == [6]  # one call, slots refilled


def test_episode_results_do_not_depend_on_slot_or_batch(runs):
    a = runs[3, False][0]
    ends = lambda eps: [(ep["success"], ep["steps"], ep["failure"]) for ep in eps]  # noqa: E731
    for key in ((4, False), (2, True), (4, True), (4, True, 2)):
        b = runs[key][0]
        assert sorted(a) == sorted(b) == sorted(TASKS)
        for task in TASKS:
            assert len(a[task]) == len(b[task]) == EPISODES
            assert all(ep["steps"] > 0 for ep in a[task])
            assert ends(a[task]) == ends(b[task]), (key, task)
