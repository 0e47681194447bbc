"""MJX against MuJoCo C on the scene: the same initial states (the env's own resets) and the
same per-physics-step controls, stepped by `mujoco.mj_step` and by MJX in float64 on CPU.

Two measures of the arm's joint-angle difference (rad):
  * free running: each simulator steps its own state N times (chaotic contact dynamics
    amplify any difference, so this grows with N);
  * one step: MJX steps once from MuJoCo C's own state before every step of C's run, which
    isolates what a single step contributes, split by whether a servo's force was clamped
    at its forcerange in that step (C's `actuator_force` at a bound of `actuator_forcerange`).
Controls come from `jump_controls` (random joint targets that jump, ramped as `env.step`
ramps them: cheap, saturates the servos often) or `expert_controls` (the scripted expert's
targets recorded in a closed-loop MJX episode and replayed open loop).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from envs import expert, physics, robot, scene
from envs.env import TabletopEnv


@dataclasses.dataclass(frozen=True)
class Starts:
    """Initial states of B envs, as float64 host arrays."""

    qpos: np.ndarray  # [B, nq]
    mocap_pos: np.ndarray  # [B, nmocap, 3]
    ctrl: np.ndarray  # [B, nu]

    def __len__(self) -> int:
        return len(self.qpos)


@dataclasses.dataclass(frozen=True)
class Agreement:
    """Arm joint-angle differences |q_C - q_MJX| (rad), max over envs and the 7 arm joints."""

    steps: int  # physics steps per env
    clamped_fraction: float  # of C's steps with any servo's force clamped
    max_dq: float  # free running, max over all steps
    final_dq: float  # free running, after the last step
    dq_before_first_clamp: float | None  # free running, max over the steps before each env's first clamped step
    dq_first_clamp: float | None  # free running, after each env's first clamped step
    one_step_clamped: float | None  # one step from C's state, max over the steps with a servo clamped
    one_step_free: float | None  # one step from C's state, max over the steps with no servo clamped
    # (None: no such step, or the one-step measure skipped)

    def row(self) -> dict:
        return dataclasses.asdict(self)


def reset_starts(env: TabletopEnv, task_ids, episodes) -> Starts:
    """The env's own evaluation initial states of (task_ids[i], episodes[i]) (`env.reset`'s,
    whose forward pass each simulator then runs itself)."""
    task_ids = np.asarray(task_ids, np.int32)
    keys = env.initial_state_keys(task_ids, episodes)
    d, _ = jax.jit(jax.vmap(env.initial_data))(keys, jnp.asarray(task_ids))
    return Starts(*(np.asarray(x, np.float64) for x in (d.qpos, d.mocap_pos, d.ctrl)))


def ramp(start: np.ndarray, targets: np.ndarray, substeps: int = scene.N_SUBSTEPS) -> np.ndarray:
    """Per-physics-step controls [B, K * substeps, nu] from control-step targets [B, K, nu]
    and the controls before the first [B, nu], as `env.step` applies them: the arm's targets
    ramp linearly over the substeps, the fingers' step."""
    prev = np.concatenate([start[:, None], targets[:, :-1]], 1)  # [B, K, nu]
    frac = np.arange(1, substeps + 1) / substeps  # [S]
    frac = np.where(np.arange(start.shape[-1]) < 7, frac[:, None], 1.0)  # [S, nu]
    ctrl = prev[:, :, None] + (targets - prev)[:, :, None] * frac  # [B, K, S, nu]
    return ctrl.reshape(start.shape[0], -1, start.shape[-1])


def jump_controls(starts: Starts, control_steps: int, seed: int = 0, jump: float = 0.1, hold: int = 2,
                  reach: float = 0.4) -> np.ndarray:
    """[B, control_steps * N_SUBSTEPS, nu]: the initial targets held for `hold` control steps,
    then every `hold` control steps each arm joint's target
    jumps by up to `jump` rad (staying within `reach` of the ready pose), and the jaw opens or
    closes at random; ramped as `env.step` does. A 0.1 rad lead over a 50 ms ramp saturates
    the servos (kp 4500 x 0.02 rad = 87 Nm), as an IK target running ahead does."""
    rng = np.random.default_rng(seed)
    b, nu = starts.ctrl.shape
    targets = np.empty((b, control_steps, nu))
    tgt = starts.ctrl.copy()
    for k in range(control_steps):
        if k and k % hold == 0:
            arm = tgt[:, :7] + rng.uniform(-jump, jump, (b, 7))
            tgt = tgt.copy()
            tgt[:, :7] = np.clip(arm, robot.HOME_QPOS - reach, robot.HOME_QPOS + reach)
            tgt[:, :7] = np.clip(tgt[:, :7], robot.ARM_LOWER, robot.ARM_UPPER)
            tgt[:, 7:] = robot.FINGER_OPEN * rng.integers(0, 2, (b, 1))
        targets[:, k] = tgt
    return ramp(starts.ctrl, targets)


def expert_controls(env: TabletopEnv, task_ids, episodes, control_steps: int) -> tuple[Starts, np.ndarray]:
    """The env's initial states and the scripted expert's controls [B, control_steps *
    substeps, nu]: its closed-loop episode in the MJX env (`env`'s own physics), the joint
    targets of each control step recorded and ramped as `env.step` ramps them."""
    starts = reset_starts(env, task_ids, episodes)
    task_ids = np.asarray(task_ids, np.int32)
    keys = env.initial_state_keys(task_ids, episodes)

    @jax.jit
    def run(keys, tids):
        state = jax.vmap(env.reset)(keys, tids)
        es = jax.vmap(lambda s: expert.init(s, env))(state)

        def body(carry, t):
            state, es = carry
            action, es = jax.vmap(lambda s, e: expert.act(env, s, e, jax.random.PRNGKey(0)))(state, es)
            state = jax.vmap(env.step)(state.replace(done=jnp.zeros_like(state.done)), action)
            return (state, es), state.data.ctrl

        return jax.lax.scan(body, (state, es), jnp.arange(control_steps))[1]  # [K, B, nu]

    targets = np.asarray(run(keys, jnp.asarray(task_ids)), np.float64).transpose(1, 0, 2)
    return starts, ramp(starts.ctrl, targets, env.config.physics.substeps)


def _c_data(m: mujoco.MjModel, starts: Starts, i: int) -> mujoco.MjData:
    d = mujoco.MjData(m)
    d.qpos[:], d.mocap_pos[:], d.ctrl[:] = starts.qpos[i], starts.mocap_pos[i], starts.ctrl[i]
    mujoco.mj_forward(m, d)
    return d


def c_rollout(m: mujoco.MjModel, starts: Starts, ctrl: np.ndarray) -> dict[str, np.ndarray]:
    """MuJoCo C, env by env: the state before each step (qpos, qvel, qacc_warmstart: what the
    next step reads) [B, N, *], qpos after each step [B, N, nq] and the force each step
    applied [B, N, nu]."""
    b, n, _ = ctrl.shape
    out = {k: np.empty((b, n, size)) for k, size in
           (("qpos0", m.nq), ("qvel0", m.nv), ("warm0", m.nv), ("qpos", m.nq), ("force", m.nu))}
    for i in range(b):
        d = _c_data(m, starts, i)
        for t in range(n):
            out["qpos0"][i, t], out["qvel0"][i, t], out["warm0"][i, t] = d.qpos, d.qvel, d.qacc_warmstart
            d.ctrl[:] = ctrl[i, t]
            mujoco.mj_step(m, d)
            out["qpos"][i, t], out["force"][i, t] = d.qpos, d.actuator_force  # force: this step's forward
    return out


def _mjx_data(m: mujoco.MjModel, starts: Starts) -> mjx.Data:
    """Batched MJX data at the initial states (MuJoCo C's forward pass of each)."""
    ds = [mjx.put_data(m, _c_data(m, starts, i)) for i in range(len(starts))]
    return jax.tree.map(lambda *x: jnp.stack(x), *ds)


def _step_batch(mx: mjx.Model, cfg: physics.PhysicsConfig, d: mjx.Data, ctrl: jnp.ndarray) -> mjx.Data:
    """One physics step of every env: d batched, ctrl [B, nu]."""
    return jax.vmap(lambda d, c: physics.step(mx, d.replace(ctrl=c), cfg))(d, ctrl)


def mjx_rollout(m: mujoco.MjModel, cfg: physics.PhysicsConfig, starts: Starts, ctrl: np.ndarray,
                compiler_options: dict | None = None) -> np.ndarray:
    """MJX, all envs at once: qpos after each step [B, N, nq]. `compiler_options` go to XLA
    (e.g. {"xla_backend_optimization_level": 0}: compiles in less than half the time, for
    short runs such as tests)."""
    mx = mjx.put_model(m)

    def run(d, ctrl):  # ctrl [N, B, nu]
        def body(d, c):
            new = _step_batch(mx, cfg, d, c)
            # put_data's integer fields are int32; under x64 mjx.step returns some as int64.
            return jax.tree.map(lambda n, o: n.astype(o.dtype), new, d), new.qpos
        return jax.lax.scan(body, d, ctrl)[1]

    args = (_mjx_data(m, starts), jnp.asarray(ctrl.transpose(1, 0, 2)))
    compiled = jax.jit(run).lower(*args).compile(compiler_options)
    return np.asarray(compiled(*args)).transpose(1, 0, 2)


def mjx_one_step(m: mujoco.MjModel, cfg: physics.PhysicsConfig, starts: Starts, c: dict[str, np.ndarray],
                 ctrl: np.ndarray, chunk: int = 256) -> np.ndarray:
    """qpos [B, N, nq] after one MJX step from each of C's states before a step (c_rollout)."""
    mx = mjx.put_model(m)
    b, n, nu = ctrl.shape
    template = mjx.put_data(m, _c_data(m, starts, 0))
    env_of = np.repeat(np.arange(b), n)
    xs = (jnp.asarray(c["qpos0"].reshape(b * n, -1)), jnp.asarray(c["qvel0"].reshape(b * n, -1)),
          jnp.asarray(c["warm0"].reshape(b * n, -1)), jnp.asarray(starts.mocap_pos[env_of]),
          jnp.asarray(ctrl.reshape(b * n, nu)))

    @jax.jit
    def one(xs):
        def f(x):
            qpos, qvel, warm, mocap, u = x
            d = template.replace(qpos=qpos, qvel=qvel, qacc_warmstart=warm, mocap_pos=mocap, ctrl=u)
            return physics.step(mx, d, cfg).qpos
        return jax.lax.map(f, xs, batch_size=chunk)

    return np.asarray(one(xs)).reshape(b, n, -1)


def compare(cfg: physics.PhysicsConfig, starts: Starts, ctrl: np.ndarray, one_step: bool = True,
            compiler_options: dict | None = None) -> Agreement:
    """MuJoCo C vs MJX under `cfg` (the scene compiled with it; MJX stepped by
    `physics.step`), float64, from `starts` under controls `ctrl` [B, N, nu]. one_step=False
    skips the one-step measure (one MJX compilation instead of two); `compiler_options`: see
    mjx_rollout."""
    m = physics.mj_model(cfg)
    arm = scene.scene_ids(m).arm_qpos
    with jax.enable_x64(True):
        c = c_rollout(m, starts, ctrl)
        free = np.abs(mjx_rollout(m, cfg, starts, ctrl, compiler_options) - c["qpos"])[..., arm].max(-1)  # [B, N]
        one = (np.abs(mjx_one_step(m, cfg, starts, c, ctrl) - c["qpos"])[..., arm].max(-1) if one_step
               else None)  # [B, N]
    clamped = np.asarray(physics.clamped(m, c["force"])).any(-1)  # [B, N]
    any_env = clamped.any(1)
    first = np.where(any_env, clamped.argmax(1), ctrl.shape[1])  # [B]
    before = np.arange(ctrl.shape[1]) < first[:, None]
    most = lambda x: float(np.max(x)) if x is not None and np.size(x) else None
    return Agreement(
        steps=int(ctrl.shape[1]),
        clamped_fraction=float(clamped.mean()),
        max_dq=float(free.max()),
        final_dq=float(free[:, -1].max()),
        dq_before_first_clamp=most(free[before]),
        dq_first_clamp=most(free[any_env, first[any_env]]),
        one_step_clamped=None if one is None else most(one[clamped]),
        one_step_free=None if one is None else most(one[~clamped]),
    )


def step_seconds(cfg: physics.PhysicsConfig, starts: Starts, ctrl: np.ndarray, reps: int = 3) -> float:
    """Seconds per batched MJX physics step (float32 as the env runs, compile excluded): `reps`
    timed calls of one jitted scan over ctrl [B, N, nu] from `starts`."""
    m = physics.mj_model(cfg)
    mx = mjx.put_model(m)
    d0 = _mjx_data(m, starts)
    u = jnp.asarray(ctrl.transpose(1, 0, 2), jnp.float32)

    @jax.jit
    def run(d):
        def body(d, c):
            return _step_batch(mx, cfg, d, c), None
        return jax.lax.scan(body, d, u)[0]

    jax.block_until_ready(run(d0))
    t0 = time.perf_counter()
    for _ in range(reps):
        jax.block_until_ready(run(d0))
    return (time.perf_counter() - t0) / (reps * ctrl.shape[1])
