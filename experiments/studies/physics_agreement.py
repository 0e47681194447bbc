"""MJX against MuJoCo C on the scene under several physics settings (envs/physics.py): how far
the arm's joints drift apart (float64, CPU), what a physics step costs in MJX, and whether the
scripted expert still succeeds.

  python -m experiments.studies.physics_agreement --measure=agreement --options=all --controls=jump,expert
  python -m experiments.studies.physics_agreement --measure=timing --options=all --time_batch=64
  python -m experiments.studies.physics_agreement --measure=success --options=current,clamp_aware --success_episodes=3

Options: `current` (the shipped scene: implicitfast, servo forcerange, MJX's own implicit
rule), `euler`, `rk4`, `unlimited` (implicitfast without forcerange), `clamp_aware`
(implicitfast, forcerange, a clamped servo's velocity derivative left out as MuJoCo C does).
Agreement (envs.physics_agreement.compare): from the env's own reset states of
--tasks_per_suite tasks of each suite x --episodes, the same per-physics-step controls,
--control_steps x 10 physics steps; `jump` controls are random joint targets that jump,
`expert` the scripted expert's targets recorded closed-loop in the (current) MJX env.
Timing: seconds per batched MJX physics step, float32, --time_batch envs (compile excluded).
Success: the expert on the first --success_episodes evaluation states of each of
--success_tasks (default: two per suite, every goal kind; the same states for every option),
camera off.
"""

from __future__ import annotations

import json
import time

from absl import app, flags, logging

import envs  # noqa: F401  (XLA CPU flags before JAX starts)
import numpy as np

from envs import physics, physics_agreement as pa, tasks as tasks_lib
from envs.env import EnvConfig, TabletopEnv
from experiments import cli
from heisd_jax import results_io
from heisd_jax.harness import evaluator as ev, methods

OPTIONS = {
    "current": physics.PhysicsConfig(),
    "euler": physics.PhysicsConfig(integrator="euler"),
    "rk4": physics.PhysicsConfig(integrator="rk4"),
    "unlimited": physics.PhysicsConfig(force_limits=False),
    "clamp_aware": physics.PhysicsConfig(clamp_aware_implicit=True),
}
MEASURES = ("agreement", "timing", "success")

FLAGS = flags.FLAGS
flags.DEFINE_list("measure", ["agreement"], f"What to measure: {', '.join(MEASURES)}.")
flags.DEFINE_list("options", ["all"], f"Physics options: {', '.join(OPTIONS)} (or all).")
flags.DEFINE_list("controls", ["jump", "expert"], "Control sources for agreement: jump, expert.")
flags.DEFINE_string("suites", "all", "Suites whose tasks are sampled.")
flags.DEFINE_integer("tasks_per_suite", 2, "Agreement: the first N tasks of each suite.", lower_bound=1)
flags.DEFINE_integer("episodes", 2, "Agreement: evaluation initial states per task.", lower_bound=1)
flags.DEFINE_integer("control_steps", 20, "Agreement: control steps (x 10 physics steps).", lower_bound=1)
flags.DEFINE_integer("seed", 0, "Agreement: seed of the jump controls.")
flags.DEFINE_integer("time_batch", 64, "Timing: envs in the batch.", lower_bound=1)
flags.DEFINE_integer("time_steps", 20, "Timing: physics steps per timed call.", lower_bound=1)
# Two tasks per suite covering every goal kind (tests/test_expert.py's sample).
flags.DEFINE_list("success_tasks", ["left_block_plate", "near_plate_cylinder_basket", "pick_purple_block",
                                    "pick_green_cylinder", "push_red_block_zone", "stack_green_on_red",
                                    "lift_blue_cylinder", "stack_red_on_blue_green_cylinder_basket"],
                  "Success: the tasks the expert runs.")
flags.DEFINE_integer("success_episodes", 5, "Success: evaluation initial states per task.", lower_bound=1)
flags.DEFINE_integer("success_envs", 40, "Success: envs in parallel.", lower_bound=1)
flags.DEFINE_string("out", "", "JSON output path (results of each measure and option are merged into it).")


def _choices(values: list[str], valid, what: str) -> list[str]:
    values = list(valid) if values == ["all"] else values
    bad = [v for v in values if v not in valid]
    if bad or not values:
        raise app.UsageError(f"unknown {what} {bad or values}; valid: {', '.join(valid)}")
    return values


def _sample(suites: str, per_suite: int) -> tuple:
    tasks = tasks_lib.get_tasks(suites)
    by_suite = {}
    for t in tasks:
        by_suite.setdefault(t.suite, []).append(t)
    return tuple(t for ts in by_suite.values() for t in ts[:per_suite])


def agreement(options: list[str], controls: list[str]) -> list[dict]:
    env = TabletopEnv(_sample(FLAGS.suites, FLAGS.tasks_per_suite), EnvConfig(render=False))
    tids = np.repeat(np.arange(len(env.tasks)), FLAGS.episodes)
    eps = np.tile(np.arange(FLAGS.episodes), len(env.tasks))
    rows = []
    for source in controls:
        if source == "jump":
            starts = pa.reset_starts(env, tids, eps)
            ctrl = pa.jump_controls(starts, FLAGS.control_steps, FLAGS.seed)
        else:
            starts, ctrl = pa.expert_controls(env, tids, eps, FLAGS.control_steps)
        for name in options:
            t0 = time.perf_counter()
            row = {"measure": "agreement", "option": name, "controls": source, "envs": len(starts),
                   **pa.compare(OPTIONS[name], starts, ctrl).row(), "seconds": time.perf_counter() - t0}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def timing(options: list[str]) -> list[dict]:
    env = TabletopEnv(config=EnvConfig(render=False))
    i = np.arange(FLAGS.time_batch)
    starts = pa.reset_starts(env, i % len(env.tasks), i // len(env.tasks))  # all tasks, then further states
    ctrl = pa.jump_controls(starts, -(-FLAGS.time_steps // 10))[:, :FLAGS.time_steps]
    rows = []
    for name in options:
        s = pa.step_seconds(OPTIONS[name], starts, ctrl)
        rows.append({"measure": "timing", "option": name, "envs": FLAGS.time_batch, "ms_per_physics_step": 1e3 * s})
        print(json.dumps(rows[-1]), flush=True)
    base = next((r["ms_per_physics_step"] for r in rows if r["option"] == "current"), None)
    for r in rows:
        r["x_current"] = r["ms_per_physics_step"] / base if base else None
    return rows


def success(options: list[str]) -> list[dict]:
    tasks = tasks_lib.get_tasks("all", FLAGS.success_tasks)
    rows = []
    for name in options:
        env = TabletopEnv(tasks, EnvConfig(render=False, physics=OPTIONS[name]))
        cfg = ev.EvalConfig(episodes_per_task=FLAGS.success_episodes, num_envs=FLAGS.success_envs)
        t0 = time.perf_counter()
        results = ev.evaluate(env, methods.make_policy("expert", env), cfg)
        summary = ev.summarize(env.tasks, results)
        failed = {k: [e for e, r in enumerate(v) if not r["success"]] for k, v in results.items()}
        rows.append({"measure": "success", "option": name, "episodes": sum(len(v) for v in results.values()),
                     "suites": {s: v["success_rate"] for s, v in summary["suites"].items()},
                     "successes": sum(r["success"] for v in results.values() for r in v),
                     "mean_steps": float(np.mean([r["steps"] for v in results.values() for r in v])),
                     "steps": {k: [r["steps"] for r in v] for k, v in results.items()},
                     "failed": {k: v for k, v in failed.items() if v}, "seconds": time.perf_counter() - t0})
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "steps"}), flush=True)
    return rows


def main(argv):
    del argv
    logging.set_verbosity(logging.WARNING)
    measures = _choices(FLAGS.measure, MEASURES, "measure")
    options = _choices(FLAGS.options, OPTIONS, "options")
    controls = _choices(FLAGS.controls, ("jump", "expert"), "controls")
    rows = []
    if "agreement" in measures:
        rows += agreement(options, controls)
    if "timing" in measures:
        rows += timing(options)
    if "success" in measures:
        rows += success(options)
    if FLAGS.out:
        try:
            old = json.load(open(FLAGS.out))
        except (OSError, ValueError):
            old = {"runs": []}
        old["runs"].append({**results_io.provenance(cli.command_line()),
                            "rows": rows})
        results_io.write_json_atomic(FLAGS.out, old)


if __name__ == "__main__":
    cli.run(main)
