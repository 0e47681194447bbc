"""A 7-DoF Franka-Panda-like arm with a parallel-jaw gripper, authored in MJCF.

Kinematics follow Franka's published (modified DH) parameters: d1=0.333, d3=0.316,
a4=0.0825, a5=-0.0825, d5=0.384, a7=0.088, flange 0.107, with Franka's joint limits,
approximate link masses, joint damping and armature. Links are visual capsules; only the
hand and the two finger pads collide (with the objects), which keeps MJX's static
collision-pair list short. Gravity compensation (`gravcomp`) plus stiff position servos
stand in for Franka's internal torque controller.
"""

from __future__ import annotations

import numpy as np

ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("finger_left", "finger_right")
# Franka joint limits (rad).
ARM_LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
ARM_UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
# Ready pose: gripper pointing down above the table, fingers open.
HOME_QPOS = np.array([0.0, -0.35, 0.0, -2.45, 0.0, 2.1, 0.785])
FINGER_OPEN = 0.04  # per-finger opening (m); the jaw opens 0.08 m in total.
EE_SITE = "tcp"
# Wrist camera, on the hand beside the jaw (hand frame: z points from the flange to the
# fingertips, the jaw opens along y): it looks down past the fingertips at the point 6 cm
# below the TCP, the fingers at the bottom edge of its image, as a Franka's wrist camera.
WRIST_CAMERA = "wrist"
WRIST_CAMERA_POS = (0.06, 0.0, 0.03)
WRIST_CAMERA_LOOK_AT = (0.0, 0.0, 0.16)
WRIST_CAMERA_FOVY = 75.0


def _wrist_xyaxes() -> str:
    """The wrist camera's image x axis along the jaw (hand y); it looks along its -z."""
    view = np.subtract(WRIST_CAMERA_LOOK_AT, WRIST_CAMERA_POS)
    z = -view / np.linalg.norm(view)
    x = np.array([0.0, 1.0, 0.0])
    return " ".join(f"{v:.6f}" for v in (*x, *np.cross(z, x)))

# Collision bits (contype / conaffinity): objects collide with everything; the environment
# (table, plate, basket) and the gripper collide only with objects.
BIT_OBJECT, BIT_ENV, BIT_GRIPPER = 1, 2, 4

_ARM_GEOM = 'contype="0" conaffinity="0" group="1"'


def robot_mjcf() -> str:
    """The arm's <body> tree (to be placed in a <worldbody>)."""
    grip = f'contype="{BIT_GRIPPER}" conaffinity="{BIT_OBJECT}" condim="3"'
    pad = f'{grip} friction="1.6 0.005 0.0001" solref="0.01 1" material="dark"'
    limits = [f"{lo:.4f} {hi:.4f}" for lo, hi in zip(ARM_LOWER, ARM_UPPER)]
    return f"""
    <body name="link0" pos="0 0 0">
      <geom type="capsule" fromto="0 0 0 0 0 0.2" size="0.07" {_ARM_GEOM} material="white"/>
      <body name="link1" pos="0 0 0.333" gravcomp="1">
        <inertial pos="0.0039 0.0021 -0.0475" mass="4.97" diaginertia="0.70 0.70 0.009"/>
        <joint name="joint1" axis="0 0 1" range="{limits[0]}"/>
        <geom type="capsule" fromto="0 0 -0.13 0 0 0" size="0.06" {_ARM_GEOM} material="white"/>
        <body name="link2" quat="1 -1 0 0" gravcomp="1">
          <inertial pos="-0.0031 -0.0283 0.0031" mass="0.646" diaginertia="0.008 0.028 0.026"/>
          <joint name="joint2" axis="0 0 1" range="{limits[1]}"/>
          <geom type="capsule" fromto="0 0 -0.06 0 0 0.06" size="0.06" {_ARM_GEOM} material="white"/>
          <geom type="capsule" fromto="0 0 0 0 -0.2 0" size="0.055" {_ARM_GEOM} material="white"/>
          <body name="link3" pos="0 -0.316 0" quat="1 1 0 0" gravcomp="1">
            <inertial pos="0.0275 0.0392 -0.0666" mass="3.228" diaginertia="0.037 0.036 0.011"/>
            <joint name="joint3" axis="0 0 1" range="{limits[2]}"/>
            <geom type="capsule" fromto="0 0 -0.12 0 0 0" size="0.055" {_ARM_GEOM} material="white"/>
            <geom type="capsule" fromto="0 0 0 0.0825 0 0" size="0.055" {_ARM_GEOM} material="white"/>
            <body name="link4" pos="0.0825 0 0" quat="1 1 0 0" gravcomp="1">
              <inertial pos="-0.0530 0.1045 0.0274" mass="3.587" diaginertia="0.026 0.019 0.029"/>
              <joint name="joint4" axis="0 0 1" range="{limits[3]}"/>
              <geom type="capsule" fromto="0 0 -0.06 0 0 0.06" size="0.055" {_ARM_GEOM} material="white"/>
              <geom type="capsule" fromto="0 0 0 -0.0825 0.1 0" size="0.055" {_ARM_GEOM} material="white"/>
              <body name="link5" pos="-0.0825 0.384 0" quat="1 -1 0 0" gravcomp="1">
                <inertial pos="-0.0120 0.0410 -0.0386" mass="1.226" diaginertia="0.036 0.029 0.009"/>
                <joint name="joint5" axis="0 0 1" range="{limits[4]}"/>
                <geom type="capsule" fromto="0 0 -0.26 0 0 -0.05" size="0.05" {_ARM_GEOM} material="white"/>
                <body name="link6" quat="1 1 0 0" gravcomp="1">
                  <inertial pos="0.0601 -0.0141 -0.0105" mass="1.666" diaginertia="0.002 0.004 0.005"/>
                  <joint name="joint6" axis="0 0 1" range="{limits[5]}"/>
                  <geom type="capsule" fromto="0 0 -0.04 0 0 0.04" size="0.05" {_ARM_GEOM} material="white"/>
                  <geom type="capsule" fromto="0 0 0 0.088 0 0" size="0.045" {_ARM_GEOM} material="white"/>
                  <body name="link7" pos="0.088 0 0" quat="1 1 0 0" gravcomp="1">
                    <inertial pos="0.0105 0.0104 0.0796" mass="0.735" diaginertia="0.012 0.010 0.005"/>
                    <joint name="joint7" axis="0 0 1" range="{limits[6]}"/>
                    <geom type="capsule" fromto="0 0 -0.03 0 0 0.07" size="0.045" {_ARM_GEOM} material="dark"/>
                    <body name="hand" pos="0 0 0.107" quat="0.9238795 0 0 -0.3826834" gravcomp="1">
                      <inertial pos="0 0 0.03" mass="0.73" diaginertia="0.0025 0.0024 0.0017"/>
                      <geom name="hand" type="box" size="0.025 0.095 0.025" pos="0 0 0.028" {grip} material="white"/>
                      <site name="{EE_SITE}" pos="0 0 0.1034" size="0.005" group="4"/>
                      <camera name="{WRIST_CAMERA}" pos="{' '.join(map(str, WRIST_CAMERA_POS))}" xyaxes="{_wrist_xyaxes()}" fovy="{WRIST_CAMERA_FOVY}"/>
                      <body name="finger_left" pos="0 0 0.0584" gravcomp="1">
                        <inertial pos="0 0.01 0.03" mass="0.015" diaginertia="2.4e-6 2.4e-6 6e-7"/>
                        <joint name="finger_left" type="slide" axis="0 1 0" range="0 {FINGER_OPEN}" damping="1" armature="0.01"/>
                        <geom name="pad_left" type="box" size="0.011 0.006 0.018" pos="0 0.006 0.036" {pad}/>
                      </body>
                      <body name="finger_right" pos="0 0 0.0584" gravcomp="1">
                        <inertial pos="0 -0.01 0.03" mass="0.015" diaginertia="2.4e-6 2.4e-6 6e-7"/>
                        <joint name="finger_right" type="slide" axis="0 -1 0" range="0 {FINGER_OPEN}" damping="1" armature="0.01"/>
                        <geom name="pad_right" type="box" size="0.011 0.006 0.018" pos="0 -0.006 0.036" {pad}/>
                      </body>
                    </body>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>"""


def actuators_mjcf(force_limits: bool = True) -> str:
    """Joint position servos: stiff on the shoulder/elbow, softer on the wrist, torque-limited
    to Franka's 87 / 12 Nm; each finger is a position servo (grip force ~ kp x closure).
    force_limits=False drops every forcerange (unlimited torques and grip force)."""
    limit = (lambda f: f' forcerange="-{f} {f}"') if force_limits else (lambda f: "")
    rows = []
    for i, (lo, hi) in enumerate(zip(ARM_LOWER, ARM_UPPER)):
        kp, kv, tau = (4500, 200, 87) if i < 4 else (2000, 60, 12)
        rows.append(
            f'<position name="a_joint{i + 1}" joint="joint{i + 1}" kp="{kp}" kv="{kv}" '
            f'ctrlrange="{lo:.4f} {hi:.4f}"{limit(tau)}/>'
        )
    for j in FINGER_JOINTS:
        rows.append(
            f'<position name="a_{j}" joint="{j}" kp="250" kv="8" ctrlrange="0 {FINGER_OPEN}"{limit(20)}/>'
        )
    return "\n    ".join(rows)
