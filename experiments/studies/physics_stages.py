"""Where one MJX physics step's time goes on a batch: each stage of MJX's forward pass jitted
alone and vmapped over --batch envs, timed on states the scripted expert reached after
--warmup control steps of an evaluation rollout (mid-episode: objects grasped, contacts live).

  python -m experiments.studies.physics_stages --batch=4096 [--physics=max_contacts=0]

Stages are timed apart, so they do not add up to the whole step exactly (each is its own
program, fused on its own). Also times the whole step with MJX's solver loop as a while loop
and as a scan of 3, 4 and 6 masked iterations (`PhysicsConfig.static_solver_loop`), and the
env's control step (IK, 10 physics steps, observations) in each case.
"""

from __future__ import annotations

import dataclasses
import time

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_driver, constraint, forward, smooth, solver

from envs import expert, physics, rollout, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from experiments import cli
from heisd_jax import results_io

FLAGS = flags.FLAGS
flags.DEFINE_integer("batch", 1024, "Envs per timed call.", lower_bound=1)
flags.DEFINE_integer("warmup", 40, "Expert control steps before timing.", lower_bound=0)
flags.DEFINE_integer("reps", 20, "Timed calls per stage.", lower_bound=1)
cli.define_physics_flag()
flags.DEFINE_string("out", "", "Optional JSON output path.")


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    cfg, n = cli.physics_config(), FLAGS.batch
    env = TabletopEnv(tasks_lib.get_tasks("all"), EnvConfig(render=False, physics=cfg))
    m = env.model
    tids, keys = env.cycling_eval_starts(n)
    state = jax.jit(lambda k, t: rollout.run_episodes(env, expert.policy(env), k, t, FLAGS.warmup)[0])(keys, tids)
    rows = []

    def timed(name, fn, x, step_cfg=cfg):
        with physics.summation_order(step_cfg):
            f = jax.jit(jax.vmap(fn))
            out = jax.block_until_ready(f(x))
        t = time.perf_counter()
        for _ in range(FLAGS.reps):
            out = f(x)
        jax.block_until_ready(out)
        rows.append({"stage": name, "ms": (time.perf_counter() - t) / FLAGS.reps * 1e3})
        print(f"{name:<44}{rows[-1]['ms']:>9.2f} ms", flush=True)
        return out

    d = state.data
    print(f"{n} envs, physics: {physics.describe(cfg) or 'defaults'}, device {jax.devices()[0].device_kind}")
    stages = [("fwd_position", lambda d: forward.fwd_position(m, d)),
              ("  kinematics + com_pos", lambda d: smooth.com_pos(m, smooth.kinematics(m, d))),
              ("  crb + factor_m", lambda d: smooth.factor_m(m, smooth.crb(m, d))),
              ("  collision", lambda d: collision_driver.collision(m, d)),
              ("  make_constraint", lambda d: constraint.make_constraint(m, d))]
    for name, fn in stages:
        timed(name, fn, d)
    d = jax.jit(jax.vmap(lambda d: forward.fwd_position(m, d)))(d)
    for name, fn in [("fwd_velocity", lambda d: forward.fwd_velocity(m, d)),
                     ("fwd_actuation + fwd_acceleration",
                      lambda d: forward.fwd_acceleration(m, forward.fwd_actuation(m, d))),
                     ("solve", lambda d: solver.solve(m, d)),
                     ("implicit integration", lambda d: forward.implicit(m, d))]:
        with physics.solver_loop(m, cfg):
            timed(name, fn, d)
        d = jax.jit(jax.vmap(fn))(d)
    for loop, iters in [("while loop", None), ("static loop", 3), ("static loop", 4), ("static loop", 6)]:
        step_cfg = dataclasses.replace(cfg, static_solver_loop=iters is not None,
                                       solver_iterations=iters or cfg.solver_iterations)
        step_env = TabletopEnv(env.tasks, EnvConfig(render=False, physics=step_cfg))
        label = f"{loop}, {step_cfg.solver_iterations} iterations"
        timed(f"physics step ({label})", lambda d: physics.step(step_env.model, d, step_cfg), state.data, step_cfg)
        timed(f"control step ({label})", lambda s: step_env.step(s, jnp.zeros(7)), state, step_cfg)
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "batch": n,
                                                 "physics": dataclasses.asdict(cfg), "rows": rows})


if __name__ == "__main__":
    cli.run(main)
