"""A 40-env expert rollout on CPU finishes (its own process, under a timeout).

On a 2-core machine with jaxlib's batched LAPACK Cholesky the rollout deadlocked for good
after compiling: both threads of XLA:CPU's intra-op pool sat in `lapack_spotrf_ffi` ->
`jax::ParallelBatchMap` (under MJX's `cho_factor` of the mass matrix / Newton Hessian,
nv = 33), which splits a large batch into tasks on that same pool and blocks until they
finish; with two such calls at once no thread is left to run the tasks. `import envs` now
lowers large batched `cholesky_p` calls on CPU to XLA's own Cholesky
(`envs._xla.cholesky_without_lapack_on_cpu`); this test keeps it so."""

import os
import subprocess
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
COMPILE_TIMEOUT = 600  # s (~2-6 min on 2 busy cores)
RUN_TIMEOUT = 120  # s after compiling; 30 control steps of 40 envs take seconds

SCRIPT = """
import faulthandler, sys
faulthandler.dump_traceback_later(float(sys.argv[3]), exit=True)  # where it is stuck, if it is
import envs  # XLA CPU flags before JAX starts
import jax, jax.numpy as jnp, numpy as np
from envs import expert, rollout, tasks
from envs.env import EnvConfig, TabletopEnv

n, steps = int(sys.argv[1]), int(sys.argv[2])
env = TabletopEnv(tasks.get_tasks("all"), EnvConfig(render=False))
tids = np.arange(n) % len(env.tasks)
keys, tids = env.initial_state_keys(tids, np.arange(n) // len(env.tasks)), jnp.asarray(tids, jnp.int32)
run = jax.jit(lambda k, t: rollout.run_episodes(env, expert.policy(env), k, t, steps)).lower(keys, tids).compile()
print("compiled", flush=True)
faulthandler.dump_traceback_later(float(sys.argv[4]), exit=True)
state, _, loop_steps = jax.device_get(run(keys, tids))
print("RESULT", int(loop_steps), bool(np.isfinite(state.data.qpos).all()), int(state.step.min()), flush=True)
"""


def test_forty_env_expert_rollout_finishes_on_cpu():
    n, steps = 40, 30
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    argv = [str(n), str(steps), str(COMPILE_TIMEOUT), str(RUN_TIMEOUT)]
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, *argv], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=COMPILE_TIMEOUT + RUN_TIMEOUT + 60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    assert proc.returncode == 0, f"{'compiled' in out and 'hung after compiling' or 'did not compile'}: {err[-3000:]}"
    (line,) = [l for l in out.splitlines() if l.startswith("RESULT ")]
    loop_steps, finite, min_step = line.split()[1:]
    assert 0 < int(loop_steps) <= steps and finite == "True" and 0 < int(min_step) <= steps
