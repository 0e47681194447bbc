"""The batched tabletop manipulation environment: pure `reset(rng, task_id)` and
`step(state, action)` over MJX, jittable and vmappable; envs in one batch may run
different tasks.

Episode bookkeeping lives in the state: `step`, `success`, `truncated` (step budget spent),
`invalid_action` (a non-finite action), `unstable` (non-finite physics), and `done`, their
union. A finished env is frozen: further steps return it unchanged, so a batch can run a
fixed number of steps while episodes end at different times. A non-finite action or a
simulator blow-up ends that env's episode as failed without touching the others.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from envs import camera, ik, language, physics, proprio, robot, rotations, scene, tasks as tasks_lib

N_LAYOUT_TRIES = 16  # candidate layouts drawn per reset; the first valid one is used


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    camera: camera.CameraConfig = camera.CameraConfig()
    control: ik.ControlConfig = ik.ControlConfig()
    render: bool = True  # False: obs.image is all zeros (for experts and physics benchmarks)
    arm_init_noise: float = 0.02  # rad, uniform noise on the ready pose at reset
    physics: physics.PhysicsConfig = physics.PhysicsConfig()  # integrator, force limits (envs/physics.py)


@struct.dataclass
class Observation:
    """What one env shows a policy at a control step (vmapped: leading batch axes). The
    fields and formats are the decode core's `heisd_jax.observation.Observation`; the
    evaluation layer converts (`heisd_jax.harness.vla_policy.observation`), so neither imports the other."""

    image: jnp.ndarray  # [H, W * n_views, 3] uint8: views tiled left to right (envs.camera)
    instruction: jnp.ndarray  # [MAX_INSTRUCTION_TOKENS] int32 ids of envs.language
    proprio: jnp.ndarray  # [8] float32: ee position, ee quaternion, jaw opening


@struct.dataclass
class EpisodeInfo:
    """What reset decided for this episode."""

    task_id: jnp.ndarray  # [] index into env.tasks
    goal_obj: jnp.ndarray  # [2] object slot of each goal (relational selectors resolved)
    colors: jnp.ndarray  # [4] palette index of each object


@struct.dataclass
class EnvState:
    data: mjx.Data
    obs: Observation  # one env's (unbatched): image [H, W * n_views, 3], instruction [L], proprio [8]
    kin: proprio.EEKinematics
    info: EpisodeInfo
    step: jnp.ndarray  # [] int32 control steps taken
    success: jnp.ndarray  # [] bool
    truncated: jnp.ndarray  # [] bool
    invalid_action: jnp.ndarray  # [] bool
    unstable: jnp.ndarray  # [] bool
    done: jnp.ndarray  # [] bool


def initial_state_key(global_task_index, episode, split: str = "eval") -> jax.Array:
    """The key of initial state `episode` of a task: the same on every machine. `split` is
    "eval" (the 50 fixed evaluation states) or "train" (demonstrations; disjoint keys)."""
    if split not in ("eval", "train"):
        raise ValueError(f"unknown split {split!r}; valid: 'eval', 'train'")
    seed = tasks_lib.EVAL_SEED if split == "eval" else tasks_lib.TRAIN_SEED
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), global_task_index), episode)


class TabletopEnv:
    """Environment over a set of tasks (default: all 40)."""

    def __init__(self, tasks: tuple[tasks_lib.Task, ...] | None = None, config: EnvConfig = EnvConfig()):
        self.tasks = tuple(tasks) if tasks else tasks_lib.ALL_TASKS
        self.config = config
        self.table = tasks_lib.compile_tasks(self.tasks)
        self.global_index = np.array([tasks_lib.ALL_TASKS.index(t) for t in self.tasks], np.int32)
        self.mj_model = physics.mj_model(config.physics)
        # This process's own device: with several processes (jax.distributed) jax.devices()[0]
        # is process 0's, which a jitted rollout elsewhere cannot close over.
        device = jax.local_devices()[0]
        self.model = mjx.put_model(self.mj_model, device=device)
        self.ids = scene.scene_ids(self.mj_model)
        self.instructions = jnp.asarray(np.stack([language.to_ids(t.instruction) for t in self.tasks]))
        self.base_rgb = jnp.asarray(self.mj_model.geom_rgba[:, :3], jnp.float32)
        self.palette = jnp.asarray(np.array(list(scene.PALETTE.values())), jnp.float32)
        d = mujoco.MjData(self.mj_model)
        d.qpos[self.ids.arm_qpos] = robot.HOME_QPOS
        d.qpos[self.ids.finger_qpos] = robot.FINGER_OPEN
        self._data0 = mjx.put_data(self.mj_model, d, device=device)

    # ---- keys -------------------------------------------------------------------------
    def initial_state_keys(self, task_ids, episodes, split: str = "eval") -> jax.Array:
        """Keys for (task_id, episode) pairs (task ids index env.tasks): [N, 2] uint32."""
        task_ids, episodes = np.broadcast_arrays(np.asarray(task_ids), np.asarray(episodes))
        g = jnp.asarray(self.global_index[task_ids.ravel()])
        return jax.vmap(lambda t, e: initial_state_key(t, e, split))(g, jnp.asarray(episodes.ravel()))

    def cycling_eval_starts(self, n: int) -> tuple[np.ndarray, jax.Array]:
        """n envs cycling over the tasks, then over their fixed evaluation initial states:
        task ids [n] int32 and initial-state keys [n, 2]."""
        i = np.arange(n)
        tids = (i % len(self.tasks)).astype(np.int32)
        return tids, self.initial_state_keys(tids, (i // len(self.tasks)) % tasks_lib.N_EVAL_INIT_STATES, split="eval")

    # ---- reset --------------------------------------------------------------------------
    def reset(self, rng: jax.Array, task_id: jnp.ndarray) -> EnvState:
        with physics.summation_order(self.config.physics):  # the forward pass and Jacobians below
            return self._reset(rng, task_id)

    def _reset(self, rng: jax.Array, task_id: jnp.ndarray) -> EnvState:
        data, info = self.initial_data(rng, task_id)
        data = physics.poses(self.model, data)  # the first step's forward pass computes the rest
        kin = proprio.ee_kinematics(self.model, data, self.ids, jnp.zeros(3), scene.CONTROL_DT)
        false = jnp.zeros((), bool)
        return EnvState(
            data=data,
            obs=self._observe(data, kin, info),
            kin=kin,
            info=info,
            step=jnp.zeros((), jnp.int32),
            success=false,
            truncated=false,
            invalid_action=false,
            unstable=false,
            done=false,
        )

    def initial_data(self, rng: jax.Array, task_id: jnp.ndarray) -> tuple[mjx.Data, EpisodeInfo]:
        """An episode's initial joint positions, receptacle poses and controls (`reset` without
        its forward pass: what a simulator needs to start the episode) and what it decided."""
        task_id = jnp.asarray(task_id, jnp.int32)
        k_layout, k_color, k_arm = jax.random.split(rng, 3)
        obj_xy, obj_yaw, rec_xy, goal_obj = self._sample_layout(k_layout, task_id)
        colors = self._sample_colors(k_color, task_id)
        ids = self.ids
        qpos = self._data0.qpos
        arm = robot.HOME_QPOS + jax.random.uniform(k_arm, (7,), minval=-1, maxval=1) * self.config.arm_init_noise
        qpos = qpos.at[ids.arm_qpos].set(arm)
        obj_z = jnp.asarray(scene.OBJECT_HALF_HEIGHT, jnp.float32)
        obj_qpos = jnp.concatenate([obj_xy, obj_z[:, None], rotations.yaw_quat(obj_yaw)], -1)  # [4, 7]
        qpos = qpos.at[ids.object_qpos[:, None] + np.arange(7)].set(obj_qpos)
        present = self.table.receptacle_present[task_id]
        rec_pos = jnp.where(present[:, None], jnp.concatenate([rec_xy, jnp.zeros((3, 1))], -1), scene.PARKED)
        mocap_pos = self._data0.mocap_pos.at[ids.mocap].set(rec_pos)
        ctrl = jnp.concatenate([arm, jnp.full((2,), robot.FINGER_OPEN)])
        data = self._data0.replace(qpos=qpos, mocap_pos=mocap_pos, ctrl=ctrl)
        return data, EpisodeInfo(task_id=task_id, goal_obj=goal_obj, colors=colors)

    def _sample_layout(self, key, task_id):
        """Object poses, receptacle positions and resolved goal objects, such that every
        relational selector's choice is unambiguous (margin >= SELECTOR_MARGIN)."""
        tbl = self.table

        def one(k):
            k_cells, k_jit, k_yaw, k_slots, k_sjit = jax.random.split(k, 5)
            cells = jax.random.permutation(k_cells, len(tasks_lib.OBJECT_CELLS))[:4]
            obj_xy = jnp.asarray(tasks_lib.OBJECT_CELLS, jnp.float32)[cells]
            obj_xy += jax.random.uniform(k_jit, (4, 2), minval=-1, maxval=1) * tasks_lib.CELL_JITTER
            yaw = jax.random.uniform(k_yaw, (4,), minval=-np.pi / 4, maxval=np.pi / 4)
            slots = jax.random.permutation(k_slots, len(tasks_lib.RECEPTACLE_SLOTS))[:3]
            slots = jnp.where(tbl.receptacle_slot[task_id] >= 0, tbl.receptacle_slot[task_id], slots)
            rec_xy = jnp.asarray(tasks_lib.RECEPTACLE_SLOTS, jnp.float32)[slots]
            rec_xy += jax.random.uniform(k_sjit, (3, 2), minval=-1, maxval=1) * tasks_lib.SLOT_JITTER
            goal_obj, margin_ok = jax.vmap(lambda s, c, o: _select(s, c, o, obj_xy, rec_xy))(
                tbl.goal_selector[task_id], tbl.goal_candidates[task_id], tbl.goal_obj[task_id]
            )
            clear = jax.vmap(lambda kind, o: _push_path_clear(kind, o, obj_xy, rec_xy[2]))(tbl.goal_kind[task_id], goal_obj)
            return obj_xy, yaw, rec_xy, goal_obj, jnp.all(margin_ok) & jnp.all(clear)

        obj_xy, yaw, rec_xy, goal_obj, ok = jax.vmap(one)(jax.random.split(key, N_LAYOUT_TRIES))
        i = jnp.argmax(ok)  # first valid candidate (0 if none, vanishingly rare)
        return obj_xy[i], yaw[i], rec_xy[i], goal_obj[i]

    def _sample_colors(self, key, task_id):
        fixed = self.table.colors[task_id]  # [4], -1 = random
        n = len(scene.COLOR_NAMES)
        used = jnp.zeros(n, bool).at[jnp.maximum(fixed, 0)].max(fixed >= 0)
        # Random colours: a random order of the palette with the fixed colours moved last.
        order = jnp.argsort(jax.random.uniform(key, (n,)) + used * 2.0)
        rank = jnp.cumsum(fixed < 0) - 1
        return jnp.where(fixed >= 0, fixed, order[jnp.clip(rank, 0, n - 1)]).astype(jnp.int32)

    # ---- step -----------------------------------------------------------------------------
    def step(self, state: EnvState, action: jnp.ndarray) -> EnvState:
        """Advances one control step (`config.physics.substeps` physics steps). Actions are clipped
        to [-1, 1]; a non-finite action fails the episode. The stages of `step_stages` in turn."""
        with physics.summation_order(self.config.physics):  # IK, physics, kinematics, Jacobians
            return self._finish(state, self._physics(state, self._controls(state, action)))

    @property
    def step_stages(self) -> tuple[Callable[[EnvState, Any], Any], ...]:
        """`step` as stages f(state, x) -> x', each of the previous one's output, the first
        of the action, the last returning the new state: the servos' targets (IK), the
        physics substeps, then the derived state and observation (camera). A rollout can
        compile each as a program of its own (XLA compiles the programs in parallel, each
        on one thread); `step` runs the same code in one program. The physics stage runs its
        solver's loop as `physics.own_program` has it (the same results either way)."""
        own = physics.own_program(self.config.physics)

        def physics_(state, controls):
            return self._physics(state, controls, own)

        def staged(fn, name):
            def stage(state, x):
                with physics.summation_order(self.config.physics):
                    return fn(state, x)
            stage.__name__ = name
            return stage
        return (staged(self._controls, "controls"), staged(physics_, "physics"), staged(self._finish, "finish"))

    def _controls(self, state: EnvState, action: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(the servos' targets [substeps, nu] of each substep, whether the action was invalid)."""
        invalid = ~jnp.all(jnp.isfinite(action))
        action = jnp.where(invalid, 0.0, action)
        target = ik.action_to_ctrl(self.model, state.data, self.ids, action, self.config.control)
        # The arm's joint targets ramp linearly over the substeps (the servos then track a
        # smooth reference, as a real arm's interpolating controller does); fingers step.
        start = state.data.ctrl
        n = self.config.physics.substeps
        frac = (jnp.arange(1, n + 1) / n)[:, None]
        return start + (target - start) * jnp.where(jnp.arange(target.shape[0]) < 7, frac, 1.0), invalid

    def _physics(self, state: EnvState, controls: tuple[jnp.ndarray, jnp.ndarray],
                 cfg: physics.PhysicsConfig | None = None) -> tuple[mjx.Data, jnp.ndarray]:
        """(the physics state after the substeps, whether the action was invalid), under `cfg`
        (default the env's physics)."""
        ramp, invalid = controls
        cfg = cfg or self.config.physics

        def substep(d, ctrl):
            return physics.step(self.model, d.replace(ctrl=ctrl), cfg), None

        data, _ = jax.lax.scan(substep, state.data, ramp)
        return data, invalid

    def _finish(self, state: EnvState, stepped: tuple[mjx.Data, jnp.ndarray]) -> EnvState:
        """The new state: derived quantities at the new positions, goals, the observation."""
        data, invalid = stepped
        data = mjx.com_pos(self.model, mjx.kinematics(self.model, data))  # derived state at the new qpos
        unstable = ~(jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel)))
        # A blown-up simulation keeps its last finite state; the episode ends as failed.
        data = jax.tree.map(lambda new, old: jnp.where(unstable, old, new), data, state.data)
        kin = proprio.ee_kinematics(self.model, data, self.ids, state.kin.lin_vel, scene.CONTROL_DT)
        step = state.step + 1
        success = state.success | (goals_achieved(self, data, state.info) & ~unstable & ~invalid)
        truncated = step >= self.table.max_steps[state.info.task_id]
        new = EnvState(
            data=data,
            obs=self._observe(data, kin, state.info),
            kin=kin,
            info=state.info,
            step=step,
            success=success,
            truncated=truncated & ~success,
            invalid_action=invalid,
            unstable=unstable,
            done=success | truncated | invalid | unstable,
        )
        return jax.tree.map(lambda old, n: jnp.where(state.done, old, n), state, new)

    def _observe(self, data: mjx.Data, kin: proprio.EEKinematics, info: EpisodeInfo) -> Observation:
        cfg = self.config.camera
        if self.config.render:
            image = camera.render_views(self.mj_model, self.model, data, self.geom_colors(info), cfg)
        else:
            image = jnp.zeros(cfg.image_shape, jnp.uint8)
        return Observation(image=image, proprio=proprio.proprio_vector(kin), instruction=self.instructions[info.task_id])

    def geom_colors(self, info: EpisodeInfo) -> jnp.ndarray:
        """[ngeom, 3] render colours with this episode's object colours."""
        return self.base_rgb.at[self.ids.object_geom].set(self.palette[info.colors])

    # ---- privileged scene readout (experts, success) --------------------------------------
    def object_pos(self, data: mjx.Data) -> jnp.ndarray:
        """[4, 3] object centres."""
        return data.qpos[self.ids.object_qpos[:, None] + np.arange(3)]

    def object_quat(self, data: mjx.Data) -> jnp.ndarray:
        return data.qpos[self.ids.object_qpos[:, None] + np.arange(3, 7)]

    def receptacle_pos(self, data: mjx.Data) -> jnp.ndarray:
        """[3, 3] plate, basket, zone base positions."""
        return data.mocap_pos[self.ids.mocap]


def _select(selector, candidates, fixed_obj, obj_xy, rec_xy):
    """Resolves one goal's object: (slot, unambiguous?)."""
    d_plate = jnp.linalg.norm(obj_xy - rec_xy[0], axis=-1)
    d_basket = jnp.linalg.norm(obj_xy - rec_xy[1], axis=-1)
    scores = jnp.stack(
        [jnp.zeros(4), obj_xy[:, 1], -obj_xy[:, 1], -obj_xy[:, 0], obj_xy[:, 0], d_plate, -d_plate, d_basket]
    )[selector]
    scores = jnp.where(candidates, scores, jnp.inf)
    order = jnp.argsort(scores)
    margin = scores[order[1]] - scores[order[0]]
    is_fixed = selector == 0
    return jnp.where(is_fixed, fixed_obj, order[0]).astype(jnp.int32), is_fixed | (margin >= tasks_lib.SELECTOR_MARGIN)


def _push_path_clear(kind, obj, obj_xy, zone_xy):
    """For a push goal: no other object within PUSH_CORRIDOR of the path from behind the
    object to the zone (other goals: always clear)."""
    p = obj_xy[obj]
    u = (zone_xy - p) / jnp.maximum(jnp.linalg.norm(zone_xy - p), 1e-6)
    a, b = p - u * 0.08, zone_xy
    t = jnp.clip(jnp.sum((obj_xy - a) * (b - a), -1) / jnp.sum((b - a) ** 2), 0.0, 1.0)
    dist = jnp.linalg.norm(obj_xy - (a + t[:, None] * (b - a)), axis=-1)
    ok = jnp.all((dist >= tasks_lib.PUSH_CORRIDOR) | (jnp.arange(4) == obj))
    return (kind != tasks_lib.GOAL_KINDS.index("push_to_zone")) | ok


def goal_status(env: TabletopEnv, data: mjx.Data, info: EpisodeInfo) -> jnp.ndarray:
    """[2] bool: whether each goal of the episode holds now (absent goals hold trivially)."""
    tbl = env.table
    pos = env.object_pos(data)
    rec = env.receptacle_pos(data)
    half_h = jnp.asarray(scene.OBJECT_HALF_HEIGHT, jnp.float32)
    kinds = tbl.goal_kind[info.task_id]

    def one(kind, obj, support):
        p, h = pos[obj], half_h[obj]
        in_box = lambda centre, half: jnp.all(jnp.abs(p[:2] - centre[:2]) < half)
        resting = lambda z: jnp.abs(p[2] - (z + h)) < 0.012
        on_plate = in_box(rec[0], scene.PLATE_HALF - 0.005) & resting(rec[0, 2] + 2 * scene.PLATE_HALF_THICK)
        in_basket = in_box(rec[1], scene.BASKET_HALF - 0.003) & (p[2] < rec[1, 2] + scene.BASKET_WALL_HEIGHT)
        in_zone = in_box(rec[2], scene.ZONE_HALF) & resting(0.0)
        s = pos[jnp.maximum(support, 0)]
        stacked = (jnp.linalg.norm(p[:2] - s[:2]) < 0.02) & resting(s[2] + half_h[jnp.maximum(support, 0)])
        lifted = p[2] > h + 0.08
        ok = jnp.stack([on_plate, in_basket, in_zone, in_zone, stacked, lifted])
        return jnp.where(kind >= 0, ok[jnp.maximum(kind, 0)], True)

    return jax.vmap(one)(kinds, info.goal_obj, tbl.goal_support[info.task_id])


def goals_achieved(env: TabletopEnv, data: mjx.Data, info: EpisodeInfo) -> jnp.ndarray:
    return jnp.all(goal_status(env, data, info))
