"""Where a rollout's compile goes: each part of an evaluation's program jitted alone, vmapped
over --num_envs envs, and traced, lowered and compiled with JAX's persistent cache off.

  python -m experiments.studies.compile_parts --method=expert --num_envs=8 [--out=compile_parts.json]

The parts: the env's reset (`initial_data`, the layout sampling inside it, `physics.poses`), its
control step (IK, one physics step, the kinematics at the new positions, the goal checks), MJX's
`kinematics` and `collision` alone, and the policy's `act`. Each compiles apart and fuses on its
own, so they do not add up to the rollout's compile (`evaluate --compile_only`) exactly; the
rollout holds one reset, one physics step (under the substeps' scan), one control step's end
and one `act`. Rows: seconds to trace, lower and compile, and the lowered StableHLO's lines.
"""

from __future__ import annotations

import dataclasses
import time

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
from mujoco import mjx

from envs import ik, physics, proprio, scene, tasks as tasks_lib
from envs.env import TabletopEnv, goals_achieved
from experiments import cli
from heisd_jax import results_io
from heisd_jax.harness import methods

FLAGS = flags.FLAGS
flags.DEFINE_enum("method", "expert", sorted(methods.METHODS), "Whose env (camera or not) and `act` to compile.")
flags.DEFINE_integer("num_envs", 8, "Envs each part is vmapped over.", lower_bound=1)
cli.define_paths("checkpoint", "drafter", "datastore")
cli.define_physics_flag()
flags.DEFINE_string("out", "", "Optional JSON output path.")


def parts(env: TabletopEnv, policy, n: int) -> dict:
    """name -> (per-env function or batched function, its inputs, whether to vmap it)."""
    m, cfg = env.model, env.config.physics
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    tids = jnp.zeros((n,), jnp.int32)
    state = jax.jit(jax.vmap(env.reset))(keys, tids)
    d, info = state.data, state.info
    pstate = policy.init(policy.params, state)
    return {
        "reset": (env.reset, (keys, tids), True),
        "reset: initial_data": (env.initial_data, (keys, tids), True),
        "reset: layout sampling": (env._sample_layout, (keys, tids), True),  # noqa: SLF001
        "reset: physics.poses": (lambda d: physics.poses(m, d), (d,), True),
        "env step": (env.step, (state, jnp.zeros((n, 7))), True),
        "step: IK": (lambda d, a: ik.action_to_ctrl(m, d, env.ids, a, env.config.control), (d, jnp.zeros((n, 7))), True),
        "step: one physics step": (lambda d: physics.step(m, d, cfg), (d,), True),
        "step: kinematics at the end": (lambda d: mjx.com_pos(m, mjx.kinematics(m, d)), (d,), True),
        "step: ee kinematics, goals": (lambda d, i: (proprio.ee_kinematics(m, d, env.ids, jnp.zeros(3), scene.CONTROL_DT),
                                                     goals_achieved(env, d, i)), (d, info), True),
        "MJX kinematics alone": (lambda d: mjx.kinematics(m, d), (d,), True),
        "MJX collision alone": (lambda d: mjx.collision(m, d), (d,), True),
        f"{policy.name} act": (lambda s, p, k: policy.act(policy.params, s, p, k), (state, pstate, keys), False),
    }


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        env_cfg = dataclasses.replace(methods.env_config(FLAGS.method, FLAGS.checkpoint), physics=cli.physics_config())
        env = TabletopEnv(tasks_lib.get_tasks("all"), env_cfg)
        policy = methods.make_policy(FLAGS.method, env, checkpoint=FLAGS.checkpoint, drafter=FLAGS.drafter,
                                     datastore=FLAGS.datastore, batch_size=FLAGS.num_envs)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    rows = []
    print(f"{'part':<32}{'trace s':>9}{'lower s':>9}{'XLA s':>8}{'StableHLO lines':>17}")
    for name, (fn, args, per_env) in parts(env, policy, FLAGS.num_envs).items():
        def batched(*a, fn=fn, per_env=per_env):
            with physics.summation_order(env.config.physics):  # as the env's own reset and step trace
                return jax.vmap(fn)(*a) if per_env else fn(*a)
        t0 = time.perf_counter()
        traced = jax.jit(batched).trace(*args)
        t1 = time.perf_counter()
        lowered = traced.lower()
        t2 = time.perf_counter()
        lowered.compile()
        t3 = time.perf_counter()
        rows.append({"part": name, "trace_s": t1 - t0, "lower_s": t2 - t1, "xla_s": t3 - t2,
                     "stablehlo_lines": lowered.as_text().count("\n")})
        print(f"{name:<32}{t1 - t0:>9.2f}{t2 - t1:>9.2f}{t3 - t2:>8.2f}{rows[-1]['stablehlo_lines']:>17}", flush=True)
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()),
                                                 "device": str(jax.devices()[0].device_kind),
                                                 "method": FLAGS.method, "num_envs": FLAGS.num_envs,
                                                 "physics": physics.describe(env.config.physics), "rows": rows})


if __name__ == "__main__":
    cli.run(main)
