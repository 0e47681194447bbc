"""The simulator's settings and its physics step: the integrator, the servos' force limits, and
how MJX's `implicitfast` treats a servo whose force is clamped.

MuJoCo C (since 3.5.0, Feb 2026: `mjd_actuator_vel` in engine_derivative.c, "skip if force is
clamped by forcerange") leaves a servo's velocity derivative (-kv) out of the implicit
integrator's matrix M - h dF/dv while the servo's force sits at its `forcerange`: the clamped
force does not depend on the velocity. MJX's JAX implementation (mujoco-mjx 3.17.0,
`mujoco/mjx/_src/derivative.py: deriv_smooth_vel`) keeps it, so under `implicitfast` it damps a
saturated joint that MuJoCo C does not, and the two drift apart from the first clamped step on
(`envs.physics_agreement` measures it). `clamp_aware_implicit=True` gives MJX MuJoCo C's rule;
the default keeps MJX's, the physics the shipped policies were trained and evaluated under.

Summation order (`fixed_order_sums`, on by default). MJX sums each body's children into its
parent (`mujoco/mjx/_src/scan.py: body_tree`, used by the Jacobians, com_pos, crb and rne) with
`jax.ops.segment_sum`, a scatter-add whose indices repeat wherever a body has several children
(the world body's: the table, the arm base, the objects; the hand's two fingers). On a GPU,
XLA runs such a scatter-add with atomic adds, so the order of the float additions, and with
it the last bit of the result, can change from run to run; contacts then amplify it into
different episodes. These are the only scatter-adds with repeated indices in the env's step
(`tests/test_physics.py` pins it). With `fixed_order_sums` they are replaced, while MJX traces,
by gathers of each parent's children added in ascending order: no atomics, the same order
every run, the same sums up to float rounding (on CPU the joints differ from MJX's own by
~1e-8 after 30 physics steps), and two evaluations of one compiled program on a GPU give
identical episodes (docs/evaluator.md).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import mujoco
from mujoco import mjx
from mujoco.mjx._src import forward as mjx_forward  # MJX's own implicitfast integrator step

from envs import scene

INTEGRATORS = ("implicitfast", "euler", "rk4")
SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}  # those MJX runs


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    integrator: str = "implicitfast"  # one of INTEGRATORS
    force_limits: bool = True  # the servos' forcerange (arm 87 / 12 Nm, fingers 20 N); False: unlimited
    # implicitfast only: leave a clamped servo's velocity derivative out of the implicit step,
    # as MuJoCo C does (False: MJX's own rule, which keeps it).
    clamp_aware_implicit: bool = False
    # MJX's sums over a body's children in a fixed order (no scatter-add atomics on a GPU).
    fixed_order_sums: bool = True
    # > 0: MJX's constraint solver takes only this many contacts per physics step, the deepest
    # (its max_contact_points), instead of every candidate slot (184, most of them inactive:
    # 745 constraint rows against 137 at 32); 0: every slot. The experts' episodes of every task
    # have at most 32 active contacts in one env (`experiments.studies.contact_pairs`): none is dropped
    # there, but the cap has no margin.
    max_contacts: int = 32
    # > 0: MJX's narrow phase tests only this many geom pairs per collision function (box-box: 19
    # pairs, box-mesh: 22), those whose bounding spheres are nearest (its max_geom_pairs); 0: all.
    # A touching pair ranks at most 8th by that measure over the experts' episodes of every task.
    max_geom_pairs: int = 10
    # The constraint solver's iteration caps. Batched (vmap), MJX's solver loop runs until every
    # env has converged, and its line search always runs all ls_iterations (a select, not a branch).
    solver_iterations: int = scene.SOLVER_ITERATIONS
    ls_iterations: int = scene.LS_ITERATIONS
    # The constraint solver (one of SOLVERS): Newton factors an nv x nv Hessian each iteration;
    # CG (Polak-Ribiere) does not, and takes more iterations to converge.
    solver: str = "newton"
    # The solver stops once its cost's improvement or gradient (scaled) falls below this
    # (scene.SOLVER_TOLERANCE says why 1e-5; 1e-8, MuJoCo's default, reproduces older results).
    tolerance: float = scene.SOLVER_TOLERANCE
    # True: the solver's loop as a scan of solver_iterations steps, each env's update masked once
    # it has converged (MJX's own stopping rule, so the same iterates and the same results),
    # instead of MJX's while loop (False), whose condition a GPU reads back to the host every
    # iteration, so a program holding it keeps its caller waiting until it ends. The scan runs
    # every iteration for every env (most converge in one or two): inside one program the
    # while loop is faster, and on a CPU always. None (the default): the scan for physics run
    # as a program of its own on a GPU (`own_program`: `TabletopEnv.step_stages`, which the
    # evaluator's queue calls step by step from the host, so the host's next calls overlap
    # the physics instead of waiting for it), else the while loop. docs/benchmark.md has the
    # measurements.
    static_solver_loop: bool | None = None
    # Physics steps per control step (scene.CONTROL_DT, 20 Hz, fixed): the timestep is
    # CONTROL_DT / substeps, 5 ms at the default 10. Fewer are cheaper per control step (the
    # env step's cost is nearly all substeps), but coarser: MuJoCo raises a contact's solref
    # time constant to at least 2 timesteps, and the arm's position servos (kp 4500, taken
    # explicitly by implicitfast) need a short enough step to stay stable (docs/benchmark.md:
    # 8 holds the expert's and AR's success, 6 does not).
    substeps: int = scene.N_SUBSTEPS

    @property
    def timestep(self) -> float:
        """One physics step (s): the control step split into `substeps`."""
        return scene.CONTROL_DT / self.substeps

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {self.integrator!r}; valid: {', '.join(INTEGRATORS)}")
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}; valid: {', '.join(SOLVERS)}")
        if not self.tolerance >= 0:
            raise ValueError(f"tolerance must be >= 0, got {self.tolerance}")
        if self.max_contacts < 0:
            raise ValueError(f"max_contacts must be 0 (every contact) or positive, got {self.max_contacts}")
        if self.max_geom_pairs < 0:
            raise ValueError(f"max_geom_pairs must be 0 (every pair) or positive, got {self.max_geom_pairs}")
        for name in ("substeps", "solver_iterations", "ls_iterations"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")


def parse(spec: str) -> PhysicsConfig:
    """A PhysicsConfig from 'field=value,...' (e.g. 'max_contacts=32,ls_iterations=4'); ''
    gives the defaults. Raises ValueError naming the valid fields for an unknown one."""
    fields = {f.name: f for f in dataclasses.fields(PhysicsConfig)}
    kwargs = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in fields:
            raise ValueError(f"physics setting {item!r}: expected field=value with a field among {', '.join(fields)}")
        default = getattr(PhysicsConfig, name)
        value = value.strip()
        if default is None or isinstance(default, bool):  # a bool, or a bool or None (its default)
            words = {"true": True, "1": True, "false": False, "0": False} | ({"none": None} if default is None else {})
            if value.lower() not in words:
                raise ValueError(f"physics setting {item!r}: {name} takes {', '.join(words)}")
            kwargs[name] = words[value.lower()]
            continue
        try:
            kwargs[name] = type(default)(value)
        except ValueError:
            raise ValueError(f"physics setting {item!r}: {name} takes a {type(default).__name__}") from None
    return PhysicsConfig(**kwargs)


def describe(cfg: PhysicsConfig) -> str:
    """The settings that differ from the defaults, as `parse` reads them ('' for the defaults)."""
    return ",".join(f"{f.name}={getattr(cfg, f.name)}" for f in dataclasses.fields(cfg)
                    if getattr(cfg, f.name) != f.default)


def collision_groups(m: mujoco.MjModel) -> dict[str, np.ndarray]:
    """MJX's collision functions on this model (e.g. 'box-mesh') -> their geom pairs [P, 2]: the
    groups within which `max_geom_pairs` keeps the nearest pairs."""
    from mujoco.mjx._src import collision_driver  # noqa: PLC0415

    out = {}
    for key, pairs in collision_driver._geom_groups(m).items():
        name = "-".join(mujoco.mjtGeom(t).name.removeprefix("mjGEOM_").lower() for t in key.types)
        pairs = np.asarray(pairs)[:, :2]
        out[name] = np.concatenate([out[name], pairs]) if name in out else pairs
    return out


def broad_phase_ranks(xpos: np.ndarray, rbound: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """[B, P] 1-based rank of each geom pair within its env by the gap between the pair's bounding
    spheres (geom positions xpos [B, ngeom, 3], radii rbound [ngeom]): the order in which MJX's
    `max_geom_pairs` keeps pairs."""
    gap = np.linalg.norm(xpos[:, pairs[:, 1]] - xpos[:, pairs[:, 0]], axis=-1) - rbound[pairs].sum(-1)
    ranks = np.empty(gap.shape, np.int64)
    np.put_along_axis(ranks, np.argsort(gap, axis=1, kind="stable"), np.arange(1, gap.shape[1] + 1)[None], axis=1)
    return ranks


@functools.lru_cache(maxsize=None)
def mj_model(cfg: PhysicsConfig = PhysicsConfig()) -> mujoco.MjModel:
    """The scene compiled with these settings (cached per setting: the model is shared)."""
    model = scene.build_model(cfg.integrator, cfg.force_limits, cfg.max_contacts, cfg.max_geom_pairs)
    options = {"iterations": cfg.solver_iterations, "ls_iterations": cfg.ls_iterations,
               "solver": SOLVERS[cfg.solver], "tolerance": cfg.tolerance, "timestep": cfg.timestep}
    if any(getattr(model.opt, k) != v for k, v in options.items()):
        model = copy.copy(model)  # the scene's own model stays as compiled
        for k, v in options.items():
            setattr(model.opt, k, v)
    return model


def clamped(m: mjx.Model, force: jnp.ndarray) -> jnp.ndarray:
    """[nu] bool: actuators whose force sits at a bound of their forcerange (MuJoCo C's test)."""
    lo, hi = m.actuator_forcerange[:, 0], m.actuator_forcerange[:, 1]
    return jnp.asarray(m.actuator_forcelimited, bool) & ((force <= lo) | (force >= hi))


def fixed_order_segment_sum(data: jnp.ndarray, segment_ids: np.ndarray, num_segments: int) -> jnp.ndarray:
    """`jax.ops.segment_sum` for segment ids known when tracing (a numpy array): each segment's
    rows gathered and added in ascending row order, with no scatter (rows with an id outside
    [0, num_segments) are dropped, as segment_sum drops them)."""
    ids = np.asarray(segment_ids)
    members = [np.flatnonzero(ids == s) for s in range(num_segments)]
    width = max((len(m) for m in members), default=0)
    if width == 0:
        return jnp.zeros((num_segments, *data.shape[1:]), data.dtype)
    rows = np.full((num_segments, width), data.shape[0])  # data.shape[0]: the zero row appended below
    for s, m in enumerate(members):
        rows[s, :len(m)] = m
    x = jnp.concatenate([data, jnp.zeros((1, *data.shape[1:]), data.dtype)])
    out = x[rows[:, 0]]
    for k in range(1, width):
        out = out + x[rows[:, k]]
    return out


def _segment_sum(original, data, segment_ids, num_segments=None, *args, **kwargs):
    if isinstance(segment_ids, np.ndarray) and num_segments is not None and not args and not kwargs:
        return fixed_order_segment_sum(data, segment_ids, num_segments)
    return original(data, segment_ids, num_segments, *args, **kwargs)


@contextlib.contextmanager
def summation_order(cfg: PhysicsConfig = PhysicsConfig()):
    """While MJX code is traced inside it (with `cfg.fixed_order_sums`), `jax.ops.segment_sum`
    over static segment ids, MJX's sum over a body's children, runs as
    `fixed_order_segment_sum`. Re-entrant; patches only tracing, not the compiled program's
    callers (the compiled program keeps whatever was traced)."""
    current = jax.ops.segment_sum
    if not cfg.fixed_order_sums or getattr(current, "_fixed_order", False):
        yield
        return
    patched = functools.partial(_segment_sum, current)
    patched._fixed_order = True
    jax.ops.segment_sum = patched
    try:
        yield
    finally:
        jax.ops.segment_sum = current


def poses(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """The part of MJX's forward pass that a reset state's observations read: body, site,
    geom and camera poses (`kinematics`, `camlight`) and the com frames Jacobians use
    (`com_pos`: cdof, subtree_com). No collision, constraints or dynamics: every step's own
    forward pass recomputes those from qpos and qvel (the solver's warm start,
    qacc_warmstart, is not a forward output), so the step after gives the same state as
    after a full `mjx.forward`, and the reset traces and compiles no second copy of the
    collision and constraint code."""
    return mjx.camlight(m, mjx.com_pos(m, mjx.kinematics(m, d)))


def solver_iterations(m: mjx.Model, d: mjx.Data, cfg: PhysicsConfig = PhysicsConfig()) -> jnp.ndarray:
    """[] int: the iterations MJX's constraint solver takes in the physics step from `d` (a state
    between steps): the forward pass up to the solve, then the solve with its loop counted (MJX
    keeps the count in its loop's state and drops it). Batched (vmap), each env's own count, not
    the batch's trip count, which is their maximum."""
    from mujoco.mjx._src import forward, solver  # noqa: PLC0415

    counts, original = [], jax.lax.while_loop

    def counted(cond_fun, body_fun, init_val):
        out = original(cond_fun, body_fun, init_val)
        counts.append(out.solver_niter)
        return out

    with summation_order(cfg):
        d = forward.fwd_acceleration(m, forward.fwd_actuation(m, forward.fwd_velocity(m, forward.fwd_position(m, d))))
        with _while_loop_as(counted):
            solver.solve(m, d)
    return counts[0] if counts else jnp.ones((), jnp.int32)  # one iteration: MJX runs it without a loop


@contextlib.contextmanager
def _while_loop_as(while_loop):
    """`jax.lax.while_loop` is `while_loop` while code is traced inside it (MJX's solver calls it
    by that name), restored after."""
    current = jax.lax.while_loop
    jax.lax.while_loop = while_loop
    try:
        yield
    finally:
        jax.lax.while_loop = current


def _static_while_loop(trip_count: int):
    """`jax.lax.while_loop` as a scan of `trip_count` steps that stops updating once `cond_fun`
    is false: the while loop's result wherever it would end within `trip_count` iterations."""
    def while_loop(cond_fun, body_fun, init_val):
        def one(val, _):
            go = cond_fun(val)
            return jax.tree.map(lambda new, old: jnp.where(go, new, old), body_fun(val), val), None
        return jax.lax.scan(one, init_val, None, length=trip_count)[0]
    return while_loop


def own_program(cfg: PhysicsConfig) -> PhysicsConfig:
    """`cfg` for physics steps compiled as a program of their own, which a host calls control
    step by control step: `static_solver_loop` None becomes True on a GPU (a while loop there
    would hold the host until it ends), False on a CPU."""
    if cfg.static_solver_loop is not None:
        return cfg
    return dataclasses.replace(cfg, static_solver_loop=jax.default_backend() == "gpu")


@contextlib.contextmanager
def solver_loop(m: mjx.Model, cfg: PhysicsConfig = PhysicsConfig()):
    """While a physics step is traced inside it (with `cfg.static_solver_loop` True; None counts
    as False here, see `own_program`), the while loop of MJX's constraint solver, the only one
    in a step (mujoco-mjx 3.17.0: `solver.solve`), runs as `_static_while_loop(m.opt.iterations)`,
    which that loop's own cap already bounds."""
    if not cfg.static_solver_loop:
        yield
        return
    with _while_loop_as(_static_while_loop(m.opt.iterations)):
        yield


def step(m: mjx.Model, d: mjx.Data, cfg: PhysicsConfig = PhysicsConfig()) -> mjx.Data:
    """One physics step: `mjx.step`, or with `cfg.clamp_aware_implicit` under implicitfast,
    MJX's forward dynamics and implicit step with the clamped servos' velocity terms zeroed;
    MJX's sums over a body's children in `cfg`'s order (`summation_order`), its solver's loop
    as `solver_loop` makes it."""
    with summation_order(cfg), solver_loop(m, cfg):
        return _step(m, d, cfg)


def _step(m: mjx.Model, d: mjx.Data, cfg: PhysicsConfig) -> mjx.Data:
    if not (cfg.clamp_aware_implicit and cfg.integrator == "implicitfast"):
        return mjx.step(m, d)
    d = mjx.forward(m, d)
    # MJX's implicit step reads each servo's velocity derivative from biasprm[:, 2] (kv of a
    # position servo) and gainprm[:, 2]; zero them for the servos clamped in this forward pass.
    free = ~clamped(m, d.actuator_force)
    m_step = m.replace(actuator_biasprm=m.actuator_biasprm.at[:, 2].multiply(free),
                       actuator_gainprm=m.actuator_gainprm.at[:, 2].multiply(free))
    return mjx_forward.implicit(m_step, d)
