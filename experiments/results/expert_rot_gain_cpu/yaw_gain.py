# The expert at several rotation gains on CPU (the figures in expert_rot_gain_cpu.json).
"""Expert success, episode length and the yaw label's saturation at several rotation gains (CPU)."""
import sys, time, json
import numpy as np, jax, jax.numpy as jnp
import envs
from envs import expert, rollout, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv

gains = [float(g) for g in sys.argv[1].split(",")]
eps = int(sys.argv[2])
task_list = tasks_lib.get_tasks("all", [])
env = TabletopEnv(task_list, EnvConfig(render=False))
n_steps = max(t.max_steps for t in task_list)
tids = np.repeat(np.arange(len(task_list)), eps)
epi = np.tile(np.arange(eps), len(task_list))
keys = env.initial_state_keys(tids, epi, split="train")
limits = jnp.asarray([task_list[t].max_steps for t in tids])
out = {}
for g in gains:
    pol = expert.policy(env, expert.ExpertConfig(rot_gain=g))
    fn = jax.jit(lambda k, t: rollout.record_episodes(env, pol, k, t, n_steps, exec_noise=0.15))
    t0 = time.time()
    final, traj = jax.block_until_ready(fn(keys, jnp.asarray(tids, jnp.int32)))
    succ = np.asarray(final.success); steps = np.asarray(final.step)
    act = np.asarray(traj["action"])  # [T, B, 7]
    mask = np.arange(act.shape[0])[:, None] < steps[None, :]
    yaw = act[..., 5][mask]; rx = act[..., 3][mask]
    per_suite = {}
    for s in sorted({t.suite for t in task_list}):
        m = np.array([task_list[t].suite == s for t in tids])
        per_suite[s] = [round(float(succ[m].mean()), 3), round(float(steps[m & succ].mean()), 1)]
    r = dict(success=round(float(succ.mean()), 4), steps_success=round(float(steps[succ].mean()), 1),
             yaw_saturated=round(float((np.abs(yaw) > 0.99).mean()), 3),
             yaw_zero=round(float((np.abs(yaw) < 1 / 128).mean()), 3),
             yaw_mid=round(float(((np.abs(yaw) >= 1 / 128) & (np.abs(yaw) <= 0.99)).mean()), 3),
             per_suite=per_suite, seconds=round(time.time() - t0, 1))
    out[g] = r
    print(g, json.dumps(r), flush=True)
