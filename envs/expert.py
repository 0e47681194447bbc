"""Scripted experts: jitted waypoint controllers using privileged object poses, acting in
the same 7-D action space as the policy.

For each goal in order, a phase machine drives the tool centre point (TCP):
  pick-and-place (plate, basket, zone, stack, lift):
    APPROACH above the object, DESCEND, GRASP (close, wait), LIFT, CARRY above the place
    point, LOWER, RELEASE (open, wait), RETREAT up;   `lift` stops after LIFT and holds.
  push (push_to_zone):
    APPROACH above a point behind the object (on the far side from the zone), DESCEND with
    the jaw closed, PUSH along the object->zone line with lateral correction, RETREAT.
While carrying, targets are expressed for the object (the TCP target is the object target
plus the current TCP-object offset), so placement heights are exact whatever the grasp.
Actions are proportional to the pose error, scaled down as a whole (direction kept) where
they would leave the action bounds; optional Gaussian action noise (not on the gripper)
diversifies demonstrations.

Phase changes depend on the state the expert sees, not only on its own path, so it can
label any state a learner reaches (DAgger): it descends from wherever the TCP is aligned
over the object at or below the hover height, and goes back to the approach when the TCP
drifts off the object's axis while descending; a dropped object restarts the goal.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import rotations, scene, tasks as tasks_lib
from envs.env import EnvState, TabletopEnv, goal_status
from envs.rollout import per_env

# Phases.
APPROACH, DESCEND, GRASP, LIFT, CARRY, LOWER, RELEASE, RETREAT, DONE = range(9)
PUSH_APPROACH, PUSH_DESCEND, PUSH, PUSH_RETREAT = range(9, 13)
PHASE_NAMES = ("approach", "descend", "grasp", "lift", "carry", "lower", "release", "retreat", "done",
               "push_approach", "push_descend", "push", "push_retreat")
# Tool orientation pointing down with yaw 0 (TCP x = world x, y = -world y, z = -world z).
R_DOWN = np.diag([1.0, -1.0, -1.0])


@dataclasses.dataclass(frozen=True)
class ExpertConfig:
    hover: float = 0.10  # m above the object before descending
    carry_height: float = 0.19  # TCP height while carrying (clears the basket walls)
    grasp_steps: int = 5  # control steps with the jaw closing before lifting
    released_opening: float = 0.07  # m: the jaw is open this wide -> the object is released, retreat
    pos_tol: float = 0.012  # m: waypoint reached
    fine_tol: float = 0.006  # m: place waypoint reached
    grasp_z_tol: float = 0.006  # m: grasp height reached ...
    grasp_xy_tol: float = 0.012  # m: ... within this of the object's axis (then close the jaw)
    gain: float = 1.2  # translation action per (error / max step)
    # Rotation action per (error / max step). At the translation's 1.2 the rotation command
    # saturates beyond ~0.1 rad of error and a step turns 1.2x the error (an overshoot); lower
    # keeps it proportional over more of a turn (docs/target.md: the expert then finishes
    # sooner and saturates fewer yaw labels).
    rot_gain: float = 1.2
    action_noise: float = 0.0  # std of Gaussian noise added to the 6 motion dims
    push_clearance: float = 0.045  # m from object centre to TCP behind it when pushing
    push_height: float = 0.022  # TCP height while pushing
    push_speed: float = 0.5  # action bound while pushing (slower than free motion)


@struct.dataclass
class ExpertState:
    goal: jnp.ndarray  # [] int, current goal index
    phase: jnp.ndarray  # [] int
    timer: jnp.ndarray  # [] int, steps spent in the phase
    yaw: jnp.ndarray  # [] float, TCP yaw held after grasping


def init(state: EnvState, env: TabletopEnv) -> ExpertState:
    kind0 = env.table.goal_kind[state.info.task_id, 0]
    phase0 = jnp.where(kind0 == tasks_lib.GOAL_KINDS.index("push_to_zone"), PUSH_APPROACH, APPROACH)
    return ExpertState(goal=jnp.zeros((), jnp.int32), phase=phase0.astype(jnp.int32), timer=jnp.zeros((), jnp.int32),
                       yaw=jnp.zeros(()))


def _saturate(v, bound):
    """v scaled down (direction kept) so that no component exceeds `bound` in magnitude:
    a far target gives a full-speed move straight at it, not a per-axis bang-bang command."""
    return v * jnp.minimum(1.0, bound / jnp.maximum(jnp.max(jnp.abs(v)), 1e-9))


def _tcp_yaw(quat):
    r = rotations.quat_to_mat(quat)
    return jnp.arctan2(r[1, 0], r[0, 0])


def _hand_clearance(yaw, p, pos, obj):
    """Smallest separation (m) between the hand's footprint, centred over `p` at `yaw`, and
    the other objects (negative: overlap)."""
    f = jnp.stack([jnp.sin(yaw), -jnp.cos(yaw)])  # finger axis (TCP y) in the world xy plane
    r = pos[:, :2] - p[:2]
    along, across = jnp.abs(r @ f), jnp.abs(r @ jnp.stack([-f[1], f[0]]))
    sep = jnp.maximum(along - 0.125, across - 0.055)
    return jnp.min(jnp.where(jnp.arange(pos.shape[0]) == obj, jnp.inf, sep))


def act(env: TabletopEnv, state: EnvState, es: ExpertState, key: jax.Array, cfg: ExpertConfig = ExpertConfig()):
    """One expert action [7] and the next expert state. Pure and jittable (vmap for batches)."""
    tbl, info = env.table, state.info
    g = jnp.minimum(es.goal, tasks_lib.MAX_GOALS - 1)
    kind = tbl.goal_kind[info.task_id, g]
    obj = info.goal_obj[g]
    support = jnp.maximum(tbl.goal_support[info.task_id, g], 0)
    pos = env.object_pos(state.data)
    quat = env.object_quat(state.data)
    rec = env.receptacle_pos(state.data)
    half = jnp.asarray(scene.OBJECT_HALF_HEIGHT, jnp.float32)
    p, h = pos[obj], half[obj]
    tcp = state.kin.pos
    is_block = jnp.asarray([s == "block" for s in scene.OBJECT_SHAPES])[obj]

    # Where the object goes (object centre), per goal kind.
    offset = jnp.concatenate([tbl.goal_offset[info.task_id, g], jnp.zeros(1)])
    rec_idx = jnp.asarray([0, 1, 2, 2, 0, 0])[jnp.maximum(kind, 0)]
    place_z = jnp.stack([
        2 * scene.PLATE_HALF_THICK + h + 0.008,  # on_plate
        scene.BASKET_WALL_HEIGHT + h + 0.01,  # in_basket: released above the walls
        h + 0.006,  # in_zone
        h,  # push_to_zone (unused)
        pos[support, 2] + half[support] + h + 0.008,  # stack_on
        h + 0.12,  # lift
    ])[jnp.maximum(kind, 0)]
    place_xy = jnp.where(kind == tasks_lib.GOAL_KINDS.index("stack_on"), pos[support, :2], rec[rec_idx, :2] + offset[:2])
    place = jnp.concatenate([place_xy, place_z[None]])

    # Grasp yaw: a block is gripped across a pair of faces, at its yaw plus a multiple of a
    # quarter turn; of those, the one nearest the hand's current yaw (a turn of at most 45
    # degrees, in the direction the relative angle of hand and block shows), or the next
    # quarter turn when only that keeps the long hand (0.19 m along the finger axis) clear of
    # the other objects. A cylinder is gripped at the current yaw (no turn). So the label is a
    # function of what the views show, not of a world-frame convention.
    cur_yaw = _tcp_yaw(state.kin.quat)
    rel = rotations.wrap_angle(rotations.quat_yaw(quat[obj]) - cur_yaw, np.pi / 2)
    yaw0 = cur_yaw + jnp.where(is_block, rel, 0.0)
    yaw1 = yaw0 - jnp.where(rel > 0, np.pi / 2, -np.pi / 2)
    clear0, clear1 = _hand_clearance(yaw0, p, pos, obj), _hand_clearance(yaw1, p, pos, obj)
    grasp_yaw = jnp.where(is_block & (clear0 < 0.0) & (clear1 > clear0 + 0.01), yaw1, yaw0)
    held = tcp - p  # TCP relative to the object (while it is held)

    # Push geometry: along the object -> zone line.
    to_zone = rec[2, :2] - p[:2]
    dist_zone = jnp.linalg.norm(to_zone)
    u = to_zone / jnp.maximum(dist_zone, 1e-6)
    behind = p[:2] - u * cfg.push_clearance
    lateral = jnp.dot(tcp[:2] - p[:2], jnp.array([-u[1], u[0]]))
    along = jnp.dot(tcp[:2] - p[:2], u)
    # The pusher slipped off the back of the object: lift and re-approach from behind.
    lost_contact = (along > -0.02) | (jnp.abs(lateral) > 0.025)
    push_xy = p[:2] + u * 0.03 - jnp.array([-u[1], u[0]]) * lateral * 1.5

    hover_z = jnp.maximum(p[2] + cfg.hover, 0.12)
    phase = es.phase
    targets = jnp.stack([
        jnp.concatenate([p[:2], hover_z[None]]),  # APPROACH
        p + jnp.array([0.0, 0.0, 0.004]),  # DESCEND
        p + jnp.array([0.0, 0.0, 0.004]),  # GRASP
        jnp.concatenate([tcp[:2], jnp.array([cfg.carry_height])]),  # LIFT
        jnp.concatenate([place_xy, jnp.array([cfg.carry_height])]) + held * jnp.array([1, 1, 0]),  # CARRY
        place + held,  # LOWER
        tcp,  # RELEASE
        jnp.concatenate([tcp[:2], jnp.array([cfg.carry_height])]),  # RETREAT
        tcp,  # DONE
        jnp.concatenate([behind, jnp.array([0.12])]),  # PUSH_APPROACH
        jnp.concatenate([behind, jnp.array([cfg.push_height])]),  # PUSH_DESCEND
        jnp.concatenate([push_xy, jnp.array([cfg.push_height])]),  # PUSH
        jnp.concatenate([tcp[:2], jnp.array([0.15])]),  # PUSH_RETREAT
    ])
    target = targets[phase]
    closed = jnp.isin(phase, jnp.array([GRASP, LIFT, CARRY, LOWER, PUSH_APPROACH, PUSH_DESCEND, PUSH, PUSH_RETREAT]))
    pre_grasp = jnp.isin(phase, jnp.array([APPROACH, DESCEND]))
    yaw = jnp.where(pre_grasp, grasp_yaw, es.yaw)

    err = target - tcp
    n_err = jnp.linalg.norm(err)
    r_des = jnp.asarray(rotations.quat_to_mat(rotations.yaw_quat(yaw))) @ R_DOWN
    r_cur = rotations.quat_to_mat(state.kin.quat)
    rot_err = rotations.mat_to_rotvec(r_des @ r_cur.T)
    motion = jnp.concatenate([
        err / env.config.control.max_pos_step * cfg.gain,
        rot_err / env.config.control.max_rot_step * cfg.rot_gain,
    ])
    bound = jnp.where(phase == PUSH, cfg.push_speed, 1.0)
    motion = jnp.concatenate([_saturate(motion[:3], bound), _saturate(motion[3:], 1.0)])
    motion = motion + cfg.action_noise * jax.random.normal(key, (6,))
    action = jnp.concatenate([jnp.clip(motion, -1, 1), jnp.where(closed, 1.0, -1.0)[None]])

    # Phase transitions.
    yaw_ok = jnp.abs(rotations.wrap_angle(cur_yaw - yaw)) < 0.08
    xy_err = jnp.linalg.norm(err[:2])
    status = goal_status(env, state.data, info)  # [2]
    goal_done = status[g]
    next_phase = jnp.select(
        [
            (phase == APPROACH) & (xy_err < cfg.pos_tol) & (err[2] > -cfg.pos_tol) & yaw_ok,
            (phase == DESCEND) & (jnp.abs(err[2]) < cfg.grasp_z_tol) & (xy_err < cfg.grasp_xy_tol),
            (phase == DESCEND) & (xy_err > 2 * cfg.pos_tol),
            (phase == GRASP) & (es.timer >= cfg.grasp_steps),
            (phase == LIFT) & (jnp.abs(err[2]) < cfg.pos_tol) & (kind != tasks_lib.GOAL_KINDS.index("lift")),
            (phase == CARRY) & (xy_err < cfg.pos_tol),
            (phase == LOWER) & (n_err < cfg.fine_tol),
            (phase == RELEASE) & (state.kin.gripper > cfg.released_opening),
            (phase == RETREAT) & (jnp.abs(err[2]) < 0.03),
            (phase == PUSH_APPROACH) & (n_err < cfg.pos_tol) & yaw_ok,
            (phase == PUSH_DESCEND) & (n_err < cfg.fine_tol),
            (phase == PUSH) & goal_done & (dist_zone < 0.02),
            (phase == PUSH) & lost_contact,
            (phase == PUSH_RETREAT) & (jnp.abs(err[2]) < 0.03),
        ],
        [DESCEND, GRASP, APPROACH, LIFT, CARRY, LOWER, RELEASE, RETREAT, DONE, PUSH_DESCEND, PUSH, PUSH_RETREAT, PUSH_APPROACH, DONE],
        phase,
    )
    # A dropped object (not near the TCP while it should be held) sends the expert back.
    dropped = jnp.isin(phase, jnp.array([LIFT, CARRY, LOWER])) & (jnp.linalg.norm(held) > 0.05)
    next_phase = jnp.where(dropped, APPROACH, next_phase)
    # States another actor (a learner, under DAgger) brought about: the object already held
    # between the jaws (grasped without this expert's descend) goes on to LIFT; a goal that
    # already holds while the expert is still on its way to it is done.
    in_hand = ((jnp.linalg.norm(held[:2]) < 0.02) & (jnp.abs(held[2] - 0.004) < 0.025)
               & (state.kin.gripper > 0.02) & (state.kin.gripper < 0.05))
    grabbed = jnp.isin(phase, jnp.array([APPROACH, DESCEND])) & in_hand & (kind != tasks_lib.GOAL_KINDS.index("push_to_zone"))
    next_phase = jnp.where(grabbed, LIFT, next_phase)
    already = jnp.isin(phase, jnp.array([APPROACH, DESCEND, PUSH_APPROACH, PUSH_DESCEND])) & goal_done & ~in_hand
    next_phase = jnp.where(already, DONE, next_phase)
    # An episode still running in DONE has a goal undone (e.g. a knocked-over stack): redo
    # the first unsatisfied goal.
    redo = (phase == DONE) & (es.timer >= 3)
    redo_goal = jnp.argmin(status).astype(jnp.int32)
    redo_kind = tbl.goal_kind[info.task_id, redo_goal]
    # After DONE, move to the next goal if there is one.
    next_goal_kind = tbl.goal_kind[info.task_id, jnp.minimum(es.goal + 1, tasks_lib.MAX_GOALS - 1)]
    advance = (next_phase == DONE) & (es.goal + 1 < tasks_lib.MAX_GOALS) & (next_goal_kind >= 0)
    first = jnp.where(next_goal_kind == tasks_lib.GOAL_KINDS.index("push_to_zone"), PUSH_APPROACH, APPROACH)
    new_goal = jnp.where(advance, es.goal + 1, es.goal)
    next_phase = jnp.where(advance, first, next_phase)
    new_goal = jnp.where(redo, redo_goal, new_goal)
    next_phase = jnp.where(redo, jnp.where(redo_kind == tasks_lib.GOAL_KINDS.index("push_to_zone"), PUSH_APPROACH, APPROACH),
                           next_phase)
    changed = next_phase != phase
    new_es = ExpertState(
        goal=new_goal.astype(jnp.int32),
        phase=next_phase.astype(jnp.int32),
        timer=jnp.where(changed, 0, es.timer + 1).astype(jnp.int32),
        yaw=jnp.where(pre_grasp, cur_yaw, es.yaw),
    )
    return action, new_es



def policy(env: TabletopEnv, cfg: ExpertConfig = ExpertConfig()):
    """The expert as an `envs.rollout.Policy`."""
    return per_env("expert", lambda s: init(s, env), lambda s, e, k: act(env, s, e, k, cfg))


def observer(env: TabletopEnv, cfg: ExpertConfig = ExpertConfig()):
    """The expert as a teacher that also reports, per env and step, the phase and goal index
    it is in (stats "phase", "goal"), e.g. to see where a learner's episodes go wrong."""
    def act_b(params, states, es, keys):
        del params
        actions, new_es = jax.vmap(lambda s, e, k: act(env, s, e, k, cfg))(states, es, keys)
        # The phase and goal the action was computed in (before this step's transition).
        return actions, new_es, {"phase": es.phase.astype(jnp.float32), "goal": es.goal.astype(jnp.float32)}

    return dataclasses.replace(policy(env, cfg), name="expert_observer", act=act_b)
