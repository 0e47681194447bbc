"""Environment throughput: the jitted, vmapped MJX env vs a per-env MuJoCo C loop, in one run.

  python -m experiments.bench_env --batch_sizes=1,16,256,1024 --out=results/bench_env.json

The baseline steps one environment at a time with `mujoco.mj_step` on the same MJCF, with
the same control step (damped-least-squares IK in NumPy, ramped joint targets, 10 physics
substeps, or as many as a --physics row's `substeps`, each with its own C loop), as
LIBERO-style evaluation runs robosuite: one env, one Python loop. MJX rows are timed with
and without the ray-cast camera, whose views are those the shipped target sees
(`methods.env_config("ar")`: the agent view and the wrist view). Compile time is excluded
(warm-up call). The C loop runs --c_reps times; ratios take its fastest repetition. A camera
row records the camera's share of the control step: 1 - its steps/s / the physics-only row's.
"""

from __future__ import annotations

import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flag before JAX starts)
from envs import physics, robot, scene
from envs.env import EnvConfig, TabletopEnv
from envs.ik import ControlConfig
from heisd_jax import results_io
from heisd_jax.harness import methods
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["1", "16", "256", "1024"], "Parallel env counts to time.")
cli.positive_int_list("batch_sizes")
flags.DEFINE_integer("steps", 20, "Control steps per timed call (one lax.scan).")
flags.DEFINE_integer("reps", 3, "Timed calls per batch size.")
flags.DEFINE_integer("c_steps", 300, "Control steps of the MuJoCo C loop, per repetition.")
flags.DEFINE_integer("c_reps", 5, "Repetitions of the MuJoCo C loop (from the same state); the fastest is the baseline.",
                     lower_bound=1)
flags.DEFINE_enum("camera", "both", ["both", "on", "off"], "Time the env with the camera, without it, or both.")
flags.DEFINE_string("physics", "", "MJX rows for each of these ';'-separated `envs.physics.PhysicsConfig` settings, "
                    "each 'field=value,...' ('' the defaults), e.g. ';max_contacts=32;max_contacts=32,ls_iterations=4'. "
                    "The C loop keeps the default settings, except `substeps`: a row's ratio is to the C loop with its substeps.")
flags.DEFINE_string("out", "", "Optional JSON output path.")


def _actions(t):
    """A smooth exploratory action sequence (same for every env and for the C loop)."""
    t = jnp.asarray(t, jnp.float32)
    return jnp.stack([0.5 * jnp.sin(0.2 * t), 0.5 * jnp.cos(0.15 * t), 0.3 * jnp.sin(0.1 * t),
                      0 * t, 0 * t, 0.2 * jnp.sin(0.3 * t), jnp.sign(jnp.sin(0.05 * t))])


def c_loop(n_steps: int, reps: int, substeps: int = scene.N_SUBSTEPS) -> list[float]:
    """Control steps per second of one env in MuJoCo C, one Python loop, for each of `reps`
    repetitions from the same state, with `substeps` physics steps per control step (the
    default settings otherwise). One repetition can run at half the speed of the next on the
    same host, so a ratio takes the fastest: the C loop at its best."""
    env = TabletopEnv(config=EnvConfig(render=False, physics=physics.PhysicsConfig(substeps=substeps)))
    m, ids, cfg = env.mj_model, env.ids, ControlConfig()
    s0 = jax.device_get(jax.jit(env.reset)(env.initial_state_keys(0, 0)[0], 0))
    acts = np.asarray(jax.vmap(_actions)(jnp.arange(n_steps)))
    return [_c_rate(m, ids, cfg, s0, acts, substeps) for _ in range(reps)]


def _c_rate(m, ids, cfg, s0, acts, substeps) -> float:
    d = mujoco.MjData(m)
    mujoco.mj_resetData(m, d)
    d.qpos[:], d.mocap_pos[:], d.ctrl[:] = s0.data.qpos, s0.data.mocap_pos, s0.data.ctrl
    mujoco.mj_forward(m, d)
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    t0 = time.perf_counter()
    for a in acts:
        mujoco.mj_jacSite(m, d, jp, jr, ids.ee_site)
        jac = np.concatenate([jp, jr])[:, ids.arm_dof]
        err = np.concatenate([a[:3] * cfg.max_pos_step, a[3:6] * cfg.max_rot_step])
        dq = jac.T @ np.linalg.solve(jac @ jac.T + cfg.ik_damping**2 * np.eye(6), err)
        q = d.qpos[ids.arm_qpos]
        target = np.clip(np.clip(d.ctrl[:7] + dq, q - cfg.max_lead, q + cfg.max_lead), robot.ARM_LOWER, robot.ARM_UPPER)
        start = d.ctrl[:7].copy()
        for i in range(substeps):
            d.ctrl[:7] = start + (target - start) * (i + 1) / substeps
            d.ctrl[7:] = robot.FINGER_OPEN * (1 - a[6]) / 2
            mujoco.mj_step(m, d)
    return len(acts) / (time.perf_counter() - t0)


def mjx_rate(n_envs: int, env_cfg: EnvConfig) -> tuple[float, float]:
    """(control steps per second summed over envs, compile seconds)."""
    env = TabletopEnv(config=env_cfg)
    tids = np.arange(n_envs) % len(env.tasks)
    state = jax.jit(jax.vmap(env.reset))(env.initial_state_keys(tids, np.arange(n_envs) // len(env.tasks)),
                                         jnp.asarray(tids, jnp.int32))
    step = jax.vmap(env.step)

    @jax.jit
    def run(state, t0):
        def body(s, t):
            return step(s, jnp.broadcast_to(_actions(t), (n_envs, 7))), None
        return jax.lax.scan(body, state, t0 + jnp.arange(FLAGS.steps))[0]

    t = time.perf_counter()
    state = jax.block_until_ready(run(state, 0))
    compile_s = time.perf_counter() - t
    # Finished envs freeze: keep them running by clearing `done` (a benchmark, not an episode).
    state = state.replace(done=jnp.zeros_like(state.done), step=jnp.zeros_like(state.step))
    t = time.perf_counter()
    for r in range(FLAGS.reps):
        state = run(state, (r + 1) * FLAGS.steps)
    jax.block_until_ready(state)
    return n_envs * FLAGS.steps * FLAGS.reps / (time.perf_counter() - t), compile_s


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    sizes = [int(b) for b in FLAGS.batch_sizes]
    try:
        configs = [physics.parse(spec) for spec in FLAGS.physics.split(";")]
    except ValueError as e:
        raise app.UsageError(f"--physics: {e}") from e
    device = str(jax.devices()[0].device_kind)
    cam = methods.env_config("ar").camera
    rows, c_best = [], {}  # the C loop at the default substeps, then at each other one a row runs
    for k in dict.fromkeys([scene.N_SUBSTEPS, *sorted(cfg.substeps for cfg in configs)]):
        reps = c_loop(FLAGS.c_steps, FLAGS.c_reps, k)
        c_best[k] = max(reps)
        rows.append({"what": "mujoco_c_loop", "n_envs": 1, "substeps": k, "ctrl_steps_per_s": c_best[k],
                     "repetitions": reps})
        print(json.dumps(rows[-1]), flush=True)
    for cfg in configs:
        for n in sizes:
            for render in {"both": [False, True], "on": [True], "off": [False]}[FLAGS.camera]:
                rate, comp = mjx_rate(n, EnvConfig(camera=cam, render=render, physics=cfg))
                rows.append({"what": "mjx", "render": render, "n_envs": n, "physics": physics.describe(cfg),
                             "ctrl_steps_per_s": rate, "compile_s": comp,
                             "x_c_loop": rate / c_best[cfg.substeps]})
                print(json.dumps(rows[-1]), flush=True)
    mjx_rows = [r for r in rows if r["what"] == "mjx"]
    physics_only = {(r["n_envs"], r["physics"]): r["ctrl_steps_per_s"] for r in mjx_rows if not r["render"]}
    for r in mjx_rows:  # the camera's share of a control step: 1 - (steps/s with it) / (steps/s without)
        if r["render"] and (r["n_envs"], r["physics"]) in physics_only:
            r["camera_share"] = 1.0 - r["ctrl_steps_per_s"] / physics_only[r["n_envs"], r["physics"]]
    print(f"\ndevice: {device}, jax {jax.__version__}, mujoco {mujoco.__version__}; camera: {', '.join(cam.views)} "
          f"({cam.height}x{cam.width}); C loop repetitions: {', '.join(f'{r:.0f}' for r in rows[0]['repetitions'])} "
          "control steps/s")
    print(f"{'env':<28}{'envs':>6}{'ctrl steps/s':>15}{'x C loop':>10}{'camera':>8}  physics")
    for r in rows:
        name = r["what"] if r["what"] != "mjx" else f"mjx {'with camera' if r['render'] else 'physics only'}"
        share = f"{r['camera_share']:.0%}" if "camera_share" in r else ""
        ratio = f"{r['x_c_loop']:.2f}" if "x_c_loop" in r else ""
        if r["what"] == "mjx":
            setting = r["physics"] or "defaults"
        else:
            setting = f"substeps={r['substeps']}" if r["substeps"] != scene.N_SUBSTEPS else ""
        print(f"{name:<28}{r['n_envs']:>6}{r['ctrl_steps_per_s']:>15.0f}{ratio:>10}{share:>8}  {setting}")
    if FLAGS.out:
        results_io.write_json_atomic(FLAGS.out, {**results_io.provenance(cli.command_line()), "device": device,
                                                 "camera": dataclasses.asdict(cam), "rows": rows})


if __name__ == "__main__":
    cli.run(main)
