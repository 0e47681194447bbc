"""The tabletop scene: the arm, a table, four graspable objects and three receptacles.

One MJCF model serves every task (MJX vmaps a single model over the batch); tasks differ
by where things are placed, by the objects' colours (a per-env rendering input, see
`envs.camera`) and by the goal. All geometry is primitive or convex:
  * blocks:    two 4 cm cubes (boxes), free bodies;
  * cylinders: two 4 cm x 6 cm cylinders, free bodies, as octagonal convex prisms (MJX has
               no cylinder-box collision and its ray caster no cylinder);
  * plate:     a thin square tray, basket: a floor and four 6 cm walls, zone: a flat
               coloured pad (visual only). All three are mocap bodies: placed per episode,
               immovable.
The table top is the plane z = 0; the arm's base stands at the origin.
"""

from __future__ import annotations

import dataclasses
import functools

import mujoco
import numpy as np

from envs import robot

TIMESTEP = 0.005  # physics step (s)
N_SUBSTEPS = 10  # physics steps per control step: 20 Hz control
CONTROL_DT = TIMESTEP * N_SUBSTEPS
SOLVER_ITERATIONS = 6  # the constraint solver's (Newton) iterations per physics step, at most
LS_ITERATIONS = 4  # its line search's iterations per solver iteration, at most
# The solver stops once its scaled cost improvement or gradient falls below this. MuJoCo's default,
# 1e-8, is below what float32 MJX reaches, so a batch ran every iteration; 1e-5 is 1.17x the
# physics throughput at 16,384 envs, the same for 1e-6 and 1e-4 (docs/benchmark.md).
SOLVER_TOLERANCE = 1e-5

BLOCK_HALF = 0.02  # half edge of the cubes (m)
CYL_RADIUS, CYL_HALF_HEIGHT = 0.02, 0.03
OBJECT_NAMES = ("block_a", "block_b", "cylinder_a", "cylinder_b")
OBJECT_SHAPES = ("block", "block", "cylinder", "cylinder")
OBJECT_HALF_HEIGHT = np.array([BLOCK_HALF, BLOCK_HALF, CYL_HALF_HEIGHT, CYL_HALF_HEIGHT])
RECEPTACLES = ("plate", "basket", "zone")
PLATE_HALF, PLATE_HALF_THICK = 0.075, 0.005
BASKET_HALF, BASKET_WALL_HEIGHT, BASKET_WALL = 0.085, 0.06, 0.006
ZONE_HALF = 0.06
PARKED = np.array([0.0, 0.0, -1.0])  # where an unused receptacle waits, under the table

# Named colours (RGB). Objects are recoloured per episode from this palette.
PALETTE = {
    "red": (0.85, 0.12, 0.10),
    "green": (0.15, 0.70, 0.20),
    "blue": (0.12, 0.30, 0.90),
    "yellow": (0.95, 0.85, 0.10),
    "purple": (0.60, 0.20, 0.75),
}
COLOR_NAMES = tuple(PALETTE)

# Agent-view camera: in front of the table, looking back at the robot (LIBERO's agentview).
CAMERA_POS = np.array([1.25, 0.0, 0.72])
CAMERA_TARGET = np.array([0.45, 0.0, 0.02])
CAMERA_FOVY = 50.0


def _cylinder_prism(n: int = 8) -> str:
    ang = np.arange(n) * 2 * np.pi / n
    pts = [(CYL_RADIUS * np.cos(a), CYL_RADIUS * np.sin(a), z) for z in (-CYL_HALF_HEIGHT, CYL_HALF_HEIGHT) for a in ang]
    return " ".join(f"{x:.5f} {y:.5f} {z:.5f}" for x, y, z in pts)


def _look_at_xyaxes(pos: np.ndarray, target: np.ndarray) -> str:
    fwd = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return " ".join(f"{v:.5f}" for v in (*right, *up))


_MJCF_INTEGRATOR = {"implicitfast": "implicitfast", "euler": "Euler", "rk4": "RK4"}


def scene_mjcf(integrator: str = "implicitfast", force_limits: bool = True, max_contacts: int = 0,
               max_geom_pairs: int = 0) -> str:
    """The full MJCF document of the scene. `integrator`: implicitfast, euler or rk4;
    `force_limits`: the servos' forcerange (False: unlimited torques); `max_contacts` > 0: MJX
    keeps only that many contacts per step, the deepest (its `max_contact_points`), so its
    constraint solver works on that many instead of every candidate's; `max_geom_pairs` > 0: MJX's
    narrow phase tests only that many geom pairs per collision function (box-box, box-mesh), those
    whose bounding spheres are nearest (its `max_geom_pairs`). MuJoCo C ignores both."""
    obj = f'contype="{robot.BIT_OBJECT}" conaffinity="{robot.BIT_OBJECT | robot.BIT_ENV | robot.BIT_GRIPPER}" condim="3" friction="1.2 0.005 0.0001" solref="0.01 1"'
    env = f'contype="{robot.BIT_ENV}" conaffinity="{robot.BIT_OBJECT}" condim="3" friction="1.0 0.005 0.0001" solref="0.01 1"'
    objects = []
    for name, shape in zip(OBJECT_NAMES, OBJECT_SHAPES):
        geom = (
            f'type="box" size="{BLOCK_HALF} {BLOCK_HALF} {BLOCK_HALF}"'
            if shape == "block"
            else 'type="mesh" mesh="cylinder"'
        )
        objects.append(
            f'<body name="{name}" pos="0.5 0 0.05"><freejoint name="{name}"/>'
            f'<geom name="{name}" {geom} mass="0.08" {obj} material="white"/></body>'
        )
    w, h, b = BASKET_HALF, BASKET_WALL_HEIGHT / 2, BASKET_WALL / 2
    walls = "".join(
        f'<geom name="basket_wall{i}" type="box" size="{sx} {sy} {h}" pos="{px} {py} {h}" {env} rgba="0.55 0.35 0.2 1" material="white"/>'
        for i, (sx, sy, px, py) in enumerate([(b, w, w, 0), (b, w, -w, 0), (w, b, 0, w), (w, b, 0, -w)])
    )
    numeric = "".join(f'\n    <numeric name="{name}" data="{n}"/>'
                      for name, n in (("max_contact_points", max_contacts), ("max_geom_pairs", max_geom_pairs)) if n > 0)
    custom = f"\n  <custom>{numeric}\n  </custom>" if numeric else ""
    return f"""<mujoco model="heisd_tabletop">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP}" iterations="{SOLVER_ITERATIONS}" ls_iterations="{LS_ITERATIONS}" tolerance="{SOLVER_TOLERANCE}" integrator="{_MJCF_INTEGRATOR[integrator]}">
    <flag eulerdamp="disable"/>
  </option>
  <default>
    <joint damping="2" armature="0.1"/>
  </default>
  <asset>
    <material name="white" rgba="1 1 1 1"/>
    <material name="dark" rgba="0.25 0.25 0.27 1"/>
    <mesh name="cylinder" vertex="{_cylinder_prism()}"/>
  </asset>
  <worldbody>
    <light pos="0.5 0 1.5" dir="0 0 -1" directional="true"/>
    <geom name="table" type="plane" size="0.6 0.7 0.01" pos="0.45 0 0" {env} rgba="0.62 0.48 0.33 1" material="white"/>
    <camera name="agentview" pos="{' '.join(map(str, CAMERA_POS))}" xyaxes="{_look_at_xyaxes(CAMERA_POS, CAMERA_TARGET)}" fovy="{CAMERA_FOVY}"/>
    {robot.robot_mjcf()}
    {''.join(objects)}
    <body name="plate" mocap="true" pos="{' '.join(map(str, PARKED))}">
      <geom name="plate" type="box" size="{PLATE_HALF} {PLATE_HALF} {PLATE_HALF_THICK}" pos="0 0 {PLATE_HALF_THICK}" {env} rgba="0.93 0.93 0.95 1" material="white"/>
    </body>
    <body name="basket" mocap="true" pos="{' '.join(map(str, PARKED))}">
      <geom name="basket_floor" type="box" size="{w} {w} {b}" pos="0 0 {b}" {env} rgba="0.55 0.35 0.2 1" material="white"/>
      {walls}
    </body>
    <body name="zone" mocap="true" pos="{' '.join(map(str, PARKED))}">
      <geom name="zone" type="box" size="{ZONE_HALF} {ZONE_HALF} 0.0005" pos="0 0 0.0005" contype="0" conaffinity="0" rgba="0.35 0.9 0.75 1" material="white"/>
    </body>
  </worldbody>
  <contact>
    <exclude body1="finger_left" body2="finger_right"/>
  </contact>{custom}
  <actuator>
    {robot.actuators_mjcf(force_limits)}
  </actuator>
</mujoco>"""


@dataclasses.dataclass(frozen=True)
class SceneIds:
    """Indices into the model's arrays, resolved once on the host."""

    arm_qpos: np.ndarray  # [7] qpos addresses of the arm joints
    arm_dof: np.ndarray  # [7] dof addresses of the arm joints
    finger_qpos: np.ndarray  # [2]
    finger_dof: np.ndarray  # [2]
    object_qpos: np.ndarray  # [4] start address of each object's 7-D free joint qpos
    object_dof: np.ndarray  # [4] start address of each object's 6-D free joint qvel
    object_body: np.ndarray  # [4]
    object_geom: np.ndarray  # [4]
    mocap: np.ndarray  # [3] mocap ids of plate, basket, zone
    ee_site: int
    hand_body: int
    pad_geoms: np.ndarray  # [2]
    camera: int  # agent view
    wrist_camera: int


def scene_ids(m: mujoco.MjModel) -> SceneIds:
    jnt = lambda n: m.joint(n)
    return SceneIds(
        arm_qpos=np.array([jnt(j).qposadr[0] for j in robot.ARM_JOINTS]),
        arm_dof=np.array([jnt(j).dofadr[0] for j in robot.ARM_JOINTS]),
        finger_qpos=np.array([jnt(j).qposadr[0] for j in robot.FINGER_JOINTS]),
        finger_dof=np.array([jnt(j).dofadr[0] for j in robot.FINGER_JOINTS]),
        object_qpos=np.array([jnt(n).qposadr[0] for n in OBJECT_NAMES]),
        object_dof=np.array([jnt(n).dofadr[0] for n in OBJECT_NAMES]),
        object_body=np.array([m.body(n).id for n in OBJECT_NAMES]),
        object_geom=np.array([m.geom(n).id for n in OBJECT_NAMES]),
        mocap=np.array([m.body_mocapid[m.body(n).id] for n in RECEPTACLES]),
        ee_site=m.site(robot.EE_SITE).id,
        hand_body=m.body("hand").id,
        pad_geoms=np.array([m.geom("pad_left").id, m.geom("pad_right").id]),
        camera=m.camera("agentview").id,
        wrist_camera=m.camera(robot.WRIST_CAMERA).id,
    )


def build_model(integrator: str = "implicitfast", force_limits: bool = True, max_contacts: int = 0,
                max_geom_pairs: int = 0) -> mujoco.MjModel:
    """Compiles the scene (cached per setting: the model is immutable and shared)."""
    return _compiled(integrator, force_limits, max_contacts, max_geom_pairs)


@functools.lru_cache(maxsize=None)
def _compiled(integrator: str, force_limits: bool, max_contacts: int, max_geom_pairs: int) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(scene_mjcf(integrator, force_limits, max_contacts, max_geom_pairs))
