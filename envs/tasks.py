"""The four task suites (LIBERO's counterparts) as data.

A task is a plain description: its instruction, the objects' colours, which receptacles
are on the table, and one or two goals achieved in order. `compile_tasks` turns a list of
tasks into fixed-shape arrays (`TaskTable`) so that a batch of environments can run
different tasks under one jitted function.

Conventions: "left"/"right" are as seen in the agent-view camera (world -y / +y), "front"
is nearer the camera (larger x), "back" nearer the robot.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import scene

GOAL_KINDS = ("on_plate", "in_basket", "in_zone", "push_to_zone", "stack_on", "lift")
SELECTORS = ("fixed", "left", "right", "front", "back", "near_plate", "far_plate", "near_basket")
RECEPTACLE_OF_GOAL = {"on_plate": 0, "in_basket": 1, "in_zone": 2, "push_to_zone": 2}
MAX_GOALS = 2
N_EVAL_INIT_STATES = 50
EVAL_SEED, TRAIN_SEED = 20260001, 7  # evaluation initial states never share keys with training
# Receptacle anchor slots (x, y) on the table; each present receptacle takes one, with jitter.
RECEPTACLE_SLOTS = np.array([[0.40, -0.25], [0.40, 0.25], [0.64, -0.23], [0.64, 0.23]])
# Object grid cells (x, y) in the middle of the table; objects take distinct cells, with jitter.
OBJECT_CELLS = np.array([[x, y] for x in (0.42, 0.52, 0.62) for y in (-0.09, 0.0, 0.09)])
SLOT_JITTER, CELL_JITTER, SELECTOR_MARGIN = 0.02, 0.015, 0.05
PUSH_CORRIDOR = 0.06  # m: other objects keep this far from a push path at reset


@dataclasses.dataclass(frozen=True)
class Goal:
    kind: str  # one of GOAL_KINDS
    obj: str  # object name (scene.OBJECT_NAMES), or with a relational selector, its shape
    selector: str = "fixed"  # one of SELECTORS: pick among objects of shape `obj` by relation
    support: str | None = None  # stack_on: the object underneath


@dataclasses.dataclass(frozen=True)
class Task:
    suite: str
    name: str
    instruction: str
    goals: tuple[Goal, ...]
    colors: tuple[str | None, ...]  # per object slot; None = random palette colour (distinct)
    receptacles: tuple[bool, bool, bool] = (True, True, False)  # plate, basket, zone present
    receptacle_slots: tuple[int, int, int] | None = None  # fixed slots (goal suite) or random
    max_steps: int = 220


def _g(kind, obj, selector="fixed", support=None):
    return Goal(kind, obj, selector, support)


def _spatial() -> list[Task]:
    rows = [
        ("left_block_plate", "pick up the block on the left and place it on the plate", _g("on_plate", "block", "left")),
        ("right_block_plate", "pick up the block on the right and place it on the plate", _g("on_plate", "block", "right")),
        ("front_block_plate", "pick up the front block and place it on the plate", _g("on_plate", "block", "front")),
        ("back_block_plate", "pick up the back block and place it on the plate", _g("on_plate", "block", "back")),
        ("near_plate_block_basket", "pick up the block closest to the plate and place it in the basket", _g("in_basket", "block", "near_plate")),
        ("far_plate_block_basket", "pick up the block farthest from the plate and place it in the basket", _g("in_basket", "block", "far_plate")),
        ("near_basket_block_plate", "pick up the block closest to the basket and place it on the plate", _g("on_plate", "block", "near_basket")),
        ("left_cylinder_basket", "pick up the cylinder on the left and place it in the basket", _g("in_basket", "cylinder", "left")),
        ("right_cylinder_basket", "pick up the cylinder on the right and place it in the basket", _g("in_basket", "cylinder", "right")),
        ("near_plate_cylinder_basket", "pick up the cylinder closest to the plate and place it in the basket", _g("in_basket", "cylinder", "near_plate")),
    ]
    colors = ("red", "red", "yellow", "yellow")  # identical objects: only the relation tells
    return [Task("spatial", n, s, (g,), colors) for n, s, g in rows]


def _object() -> list[Task]:
    tasks = []
    for shape, slot in (("block", 0), ("cylinder", 2)):
        for color in scene.COLOR_NAMES:
            colors = [None] * 4
            colors[slot] = color
            tasks.append(
                Task(
                    "object",
                    f"pick_{color}_{shape}",
                    f"pick up the {color} {shape} and place it in the basket",
                    (_g("in_basket", scene.OBJECT_NAMES[slot]),),
                    tuple(colors),
                )
            )
    return tasks


def _goal() -> list[Task]:
    colors = ("red", "green", "yellow", "blue")
    rows = [
        ("red_block_plate", "put the red block on the plate", (_g("on_plate", "block_a"),)),
        ("green_block_basket", "put the green block in the basket", (_g("in_basket", "block_b"),)),
        ("push_red_block_zone", "push the red block into the target zone", (_g("push_to_zone", "block_a"),)),
        ("stack_red_on_green", "stack the red block on the green block", (_g("stack_on", "block_a", support="block_b"),)),
        ("yellow_cylinder_plate", "put the yellow cylinder on the plate", (_g("on_plate", "cylinder_a"),)),
        ("blue_cylinder_basket", "put the blue cylinder in the basket", (_g("in_basket", "cylinder_b"),)),
        ("stack_green_on_red", "stack the green block on the red block", (_g("stack_on", "block_b", support="block_a"),)),
        ("yellow_cylinder_zone", "put the yellow cylinder in the target zone", (_g("in_zone", "cylinder_a"),)),
        ("lift_blue_cylinder", "pick up the blue cylinder and hold it up", (_g("lift", "cylinder_b"),)),
        ("push_green_block_zone", "push the green block into the target zone", (_g("push_to_zone", "block_b"),)),
    ]
    return [Task("goal", n, s, gs, colors, (True, True, True), (0, 1, 2)) for n, s, gs in rows]


def _long() -> list[Task]:
    rows = [
        ("red_green_blocks_basket", ("red", "green", "blue", "yellow"), "put the red block and the green block in the basket",
         (_g("in_basket", "block_a"), _g("in_basket", "block_b"))),
        ("both_cylinders_basket", ("blue", "red", "yellow", "purple"), "put the yellow cylinder and the purple cylinder in the basket",
         (_g("in_basket", "cylinder_a"), _g("in_basket", "cylinder_b"))),
        ("blue_block_plate_red_cylinder_basket", ("blue", "yellow", "red", "green"), "put the blue block on the plate and the red cylinder in the basket",
         (_g("on_plate", "block_a"), _g("in_basket", "cylinder_a"))),
        ("green_cylinder_basket_yellow_block_plate", ("yellow", "purple", "green", "blue"), "put the green cylinder in the basket and the yellow block on the plate",
         (_g("in_basket", "cylinder_a"), _g("on_plate", "block_a"))),
        ("stack_red_on_blue_green_cylinder_basket", ("red", "blue", "green", "yellow"), "stack the red block on the blue block and put the green cylinder in the basket",
         (_g("stack_on", "block_a", support="block_b"), _g("in_basket", "cylinder_a"))),
        ("purple_block_zone_blue_cylinder_plate", ("purple", "green", "blue", "red"), "put the purple block in the target zone and the blue cylinder on the plate",
         (_g("in_zone", "block_a"), _g("on_plate", "cylinder_a"))),
        ("red_cylinder_plate_green_block_basket", ("green", "blue", "red", "yellow"), "put the red cylinder on the plate and the green block in the basket",
         (_g("on_plate", "cylinder_a"), _g("in_basket", "block_a"))),
        ("yellow_block_basket_blue_cylinder_zone", ("yellow", "red", "blue", "purple"), "put the yellow block in the basket and the blue cylinder in the target zone",
         (_g("in_basket", "block_a"), _g("in_zone", "cylinder_a"))),
        ("blue_block_yellow_cylinder_plate", ("blue", "green", "yellow", "red"), "put the blue block and the yellow cylinder on the plate",
         (_g("on_plate", "block_a"), _g("on_plate", "cylinder_a"))),
        ("purple_cylinder_basket_red_block_zone", ("red", "yellow", "purple", "green"), "put the purple cylinder in the basket and the red block in the target zone",
         (_g("in_basket", "cylinder_a"), _g("in_zone", "block_a"))),
    ]
    tasks = []
    for n, colors, s, gs in rows:
        zone = any(g.kind in ("in_zone", "push_to_zone") for g in gs)
        tasks.append(Task("long", n, s, gs, colors, (True, True, zone), None, 420))
    return tasks


SUITES: dict[str, tuple[Task, ...]] = {
    "spatial": tuple(_spatial()),
    "object": tuple(_object()),
    "goal": tuple(_goal()),
    "long": tuple(_long()),
}
ALL_TASKS: tuple[Task, ...] = tuple(t for s in SUITES.values() for t in s)
TASK_NAMES: frozenset[str] = frozenset(t.name for t in ALL_TASKS)


def get_tasks(suites: str | list[str] = "all", tasks: list[str] | None = None) -> tuple[Task, ...]:
    """Tasks of the named suites (comma string or list; "all"), optionally only the named ones.

    Raises ValueError naming the valid choices for an unknown suite or task.
    """
    names = list(SUITES) if suites == "all" else (suites.split(",") if isinstance(suites, str) else list(suites))
    names = [n.strip() for n in names if n.strip()]
    bad = [n for n in names if n not in SUITES]
    if bad or not names:
        raise ValueError(f"unknown suite(s) {bad or names}; valid suites: {', '.join(SUITES)} (or 'all')")
    chosen = [t for n in names for t in SUITES[n]]
    if tasks:
        by_name = {t.name: t for t in chosen}
        bad = [n for n in tasks if n not in by_name]
        if bad:
            raise ValueError(f"unknown task(s) {bad} in suite(s) {names}; valid tasks: {', '.join(by_name)}")
        chosen = [by_name[n] for n in tasks]
    return tuple(chosen)


@struct.dataclass
class TaskTable:
    """Fixed-shape arrays describing T tasks; indexed by a per-env task id inside jit."""

    goal_kind: jnp.ndarray  # [T, 2] int, index into GOAL_KINDS; -1 = no goal
    goal_obj: jnp.ndarray  # [T, 2] int, object slot for a fixed selector
    goal_selector: jnp.ndarray  # [T, 2] int, index into SELECTORS
    goal_candidates: jnp.ndarray  # [T, 2, 4] bool, objects a relational selector chooses among
    goal_support: jnp.ndarray  # [T, 2] int, object slot underneath (stack_on), else -1
    goal_offset: jnp.ndarray  # [T, 2, 2] where in the receptacle to put the object (m)
    colors: jnp.ndarray  # [T, 4] int palette index, -1 = random
    receptacle_present: jnp.ndarray  # [T, 3] bool
    receptacle_slot: jnp.ndarray  # [T, 3] int fixed anchor slot, -1 = random
    max_steps: jnp.ndarray  # [T] int


def compile_tasks(tasks: tuple[Task, ...]) -> TaskTable:
    t = len(tasks)
    kind = -np.ones((t, MAX_GOALS), np.int32)
    obj = np.zeros((t, MAX_GOALS), np.int32)
    sel = np.zeros((t, MAX_GOALS), np.int32)
    cands = np.zeros((t, MAX_GOALS, 4), bool)
    support = -np.ones((t, MAX_GOALS), np.int32)
    offset = np.zeros((t, MAX_GOALS, 2), np.float32)
    colors = -np.ones((t, 4), np.int32)
    present = np.zeros((t, 3), bool)
    slot = -np.ones((t, 3), np.int32)
    for i, task in enumerate(tasks):
        for j, g in enumerate(task.goals):
            kind[i, j] = GOAL_KINDS.index(g.kind)
            sel[i, j] = SELECTORS.index(g.selector)
            if g.selector == "fixed":
                obj[i, j] = scene.OBJECT_NAMES.index(g.obj)
                cands[i, j, obj[i, j]] = True
            else:
                cands[i, j] = [s == g.obj for s in scene.OBJECT_SHAPES]
            if g.support is not None:
                support[i, j] = scene.OBJECT_NAMES.index(g.support)
        recs = [RECEPTACLE_OF_GOAL.get(g.kind) for g in task.goals]
        if len(recs) == 2 and recs[0] is not None and recs[0] == recs[1]:
            offset[i, :, 1] = (-0.035, 0.035)  # two objects into one receptacle: side by side
        for k, c in enumerate(task.colors):
            colors[i, k] = -1 if c is None else scene.COLOR_NAMES.index(c)
        present[i] = task.receptacles
        if task.receptacle_slots is not None:
            slot[i] = task.receptacle_slots
    return TaskTable(
        goal_kind=jnp.asarray(kind),
        goal_obj=jnp.asarray(obj),
        goal_selector=jnp.asarray(sel),
        goal_candidates=jnp.asarray(cands),
        goal_support=jnp.asarray(support),
        goal_offset=jnp.asarray(offset),
        colors=jnp.asarray(colors),
        receptacle_present=jnp.asarray(present),
        receptacle_slot=jnp.asarray(slot),
        max_steps=jnp.asarray([task.max_steps for task in tasks], jnp.int32),
    )


def parse_suite_weights(items: Sequence[str]) -> dict[str, int]:
    """Multipliers of the episodes collected per task, from "SUITE:N" or "TASK:N" entries: a
    suite's weight applies to each of its tasks, a task's own weight overrides it, anything not
    named gets 1 (`episode_weight`). ValueError naming the bad entry and the valid suites."""
    out = {}
    for item in items:
        name, sep, n = str(item).partition(":")
        if not sep or (name not in SUITES and name not in TASK_NAMES) or not n.strip().isdigit() or int(n) < 1:
            raise ValueError(f"bad suite weight {item!r}: expected SUITE:N or TASK:N with N >= 1, SUITE one of "
                             f"{list(SUITES)} and TASK a task name of those suites")
        out[name] = int(n)
    return out


def failure_weights(success_rate: dict[str, float], max_weight: int = 4) -> list[str]:
    """"TASK:N" weights (for `parse_suite_weights`) that give each task episodes in proportion to
    how often a policy failed it: N = 1 + round(10 x failure rate), at most `max_weight`; tasks
    at N = 1 are left out. A task failed 1 time in 3 gets 4x, 1 in 10 gets 2x. The next DAgger
    round then visits most the states where the policy goes wrong. ValueError for a name that is
    no task or a rate outside [0, 1]."""
    out = []
    for name, rate in success_rate.items():
        if name not in TASK_NAMES or not 0.0 <= rate <= 1.0:
            raise ValueError(f"bad task success rate {name!r}: {rate!r} (expected a task name and a rate in [0, 1])")
        n = min(max_weight, 1 + int(round(10 * (1.0 - rate))))
        if n > 1:
            out.append(f"{name}:{n}")
    return out


def episode_weight(task: Task, weights: dict[str, int]) -> int:
    """How many times the per-task episode count `task` gets under `parse_suite_weights`' weights."""
    return weights.get(task.name, weights.get(task.suite, 1))


def episode_counts(tasks: Sequence[Task], per_task: int, weights: dict[str, int], total: int | None = None
                   ) -> dict[str, int]:
    """Episodes to collect per task: `per_task` x its weight (`episode_weight`); with `total`,
    those counts scaled to add up to `total` (largest remainders rounded up, every task at
    least 1), so that weights move episodes between tasks instead of adding them. ValueError
    when `total` is smaller than the number of tasks."""
    counts = {t.name: per_task * episode_weight(t, weights) for t in tasks}
    if total is None:
        return counts
    if total < len(counts):
        raise ValueError(f"{total} episodes cannot give each of {len(counts)} tasks one")
    spare = total - len(counts)  # one each first, the rest in proportion to the counts
    scale = spare / sum(counts.values())
    exact = {name: c * scale for name, c in counts.items()}
    out = {name: 1 + int(x) for name, x in exact.items()}
    by_remainder = sorted(exact, key=lambda name: (int(exact[name]) - exact[name], name))
    for name in by_remainder[:total - sum(out.values())]:
        out[name] += 1
    return out


def shared_episode_counts(tasks: Sequence[Task], per_task: int, given: dict[str, int], weights: dict[str, int]
                          ) -> dict[str, int]:
    """Episodes per task when `weights` (the failures' added to `given`) share out what `given`
    alone would collect, time limit by time limit: the tasks of one `max_steps` keep their
    combined count, and the weights move episodes between them (`episode_counts` with that
    count as the total). A collection batches episodes by time limit (a batch runs to its
    longest task's limit), so each limit keeping its count keeps every batch's shape, and
    every round of a build runs the one compiled program whatever its failures."""
    out = {}
    for limit in sorted({t.max_steps for t in tasks}):
        group = [t for t in tasks if t.max_steps == limit]
        total = sum(episode_counts(group, per_task, given).values())
        out.update(episode_counts(group, per_task, weights, total))
    return {t.name: out[t.name] for t in tasks}
