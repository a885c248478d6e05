"""A parallel-jaw gripper (85 mm stroke class) for the flange of any arm.

One position-servoed slide joint drives the left finger; an equality constraint mirrors
it on the right. The actuator's control is the episode contract's gripper command in
[0, 1] (0 open, 1 closed); the closing force saturates at :data:`MAX_FORCE` newtons, so
a closed gripper squeezes an object with a bounded force like a real one.
"""

from __future__ import annotations

import mujoco
import numpy as np

STROKE = 0.04  # per finger (m): opening goes from 2 * STROKE to 0
MAX_FORCE = 60.0  # N, closing force limit
SERVO_KP = 2500.0  # N/m
SERVO_KV = 400.0  # N s/m: closing speed saturates near 0.15 m/s
TCP_OFFSET = 0.125  # m from the flange along the tool axis: between the fingertips
FINGER_LENGTH = 0.06
PAD_FRICTION = (1.5, 0.02, 0.0001)

JOINT = "gripper_finger"
MIRROR_JOINT = "gripper_finger_mirror"
ACTUATOR = "gripper"
TCP_SITE = "tcp"


def add_parallel_gripper(flange: mujoco.MjsBody, spec: mujoco.MjSpec) -> None:
    """Add the gripper to ``flange`` (tool axis = flange +z), its actuator and TCP site."""
    gray, dark = [0.2, 0.2, 0.22, 1], [0.1, 0.1, 0.1, 1]
    body = flange.add_body(name="gripper_base")
    body.gravcomp = 1.0
    body.add_geom(
        name="gripper_coupling",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.038, 0.01, 0],
        pos=[0, 0, 0.01],
        rgba=dark,
        mass=0.15,
        contype=1,
        conaffinity=0,
    )
    body.add_geom(
        name="gripper_palm",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.022, 0.055, 0.022],
        pos=[0, 0, 0.042],
        rgba=gray,
        mass=0.6,
        contype=1,
        conaffinity=0,
    )
    body.add_site(
        name=TCP_SITE, pos=[0, 0, TCP_OFFSET], size=[0.005, 0, 0], rgba=[1, 0, 0, 0], group=3
    )
    base_z = 0.064
    for side, joint_name in ((1, JOINT), (-1, MIRROR_JOINT)):
        finger = body.add_body(name=f"gripper_finger_{'left' if side > 0 else 'right'}")
        finger.gravcomp = 1.0
        finger.pos = [0, 0, base_z]
        finger.add_joint(
            name=joint_name,
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=[0, -side, 0],
            range=[0, STROKE],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            # Servo damping as joint damping: integrated implicitly, stable when saturated.
            damping=SERVO_KV,
            armature=0.01,
        )
        finger.add_geom(
            name=f"gripper_pad_{'left' if side > 0 else 'right'}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.011, 0.006, FINGER_LENGTH / 2],
            pos=[0, side * (STROKE + 0.006), FINGER_LENGTH / 2 + 0.004],
            rgba=dark,
            mass=0.05,
            friction=PAD_FRICTION,
            condim=4,
            solref=[0.004, 1.0],  # stiff pads: a 60 N squeeze sinks in about a millimetre
            solimp=[0.95, 0.99, 0.001, 0.5, 2.0],
            contype=1,
            conaffinity=0,
            priority=1,
        )
    spec.add_equality(
        type=mujoco.mjtEq.mjEQ_JOINT,
        name1=MIRROR_JOINT,
        name2=JOINT,
        data=[0, 1, 0, 0, 0] + [0] * 7,
        solref=[0.005, 1],
    )
    act = spec.add_actuator(name=ACTUATOR, target=JOINT, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
    act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
    act.gainprm = [SERVO_KP * STROKE] + [0] * 9
    act.biasprm = [0, -SERVO_KP, 0] + [0] * 7
    act.ctrlrange = [0, 1]
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.forcerange = [-MAX_FORCE, MAX_FORCE]
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


def opening_from_joint(finger_qpos: float) -> float:
    """Distance between the finger pads (m) for the driven finger's joint position."""
    return 2.0 * (STROKE - finger_qpos)


def joint_from_opening(opening: float | np.ndarray) -> float | np.ndarray:
    """The driven finger's joint position for a distance between the pads (m), within
    its stroke (the inverse of :func:`opening_from_joint`)."""
    return np.clip(STROKE - np.asarray(opening) / 2.0, 0.0, STROKE)
