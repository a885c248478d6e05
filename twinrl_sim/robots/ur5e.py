"""Universal Robots UR5e built from its published parameters.

Kinematics are the standard Denavit-Hartenberg parameters Universal Robots publish for the
UR5e; masses and centres of mass come from the same table (centres of mass expressed in
the DH link frames). Inertia tensors are not published: each link's is that of a solid
cylinder of the link's mass around the link's main axis, which is what MuJoCo needs and
close enough for a position-servoed arm.

The body tree mirrors the DH chain: body ``link{i}`` sits in DH frame ``i-1`` and its
hinge turns about the local z axis, so its child is placed at ``(a_i, 0, d_i)`` rotated
by ``Rx(alpha_i)``. With all joints at zero the model is in UR's zero pose (arm straight
out along the base's -x axis is *not* assumed: the DH zero pose is what it is).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

# Published DH parameters (metres, radians).
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
DH_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)

# Published dynamics: link masses (kg) and centres of mass in the DH link frames (m).
LINK_MASSES = (3.761, 8.058, 2.846, 1.37, 1.3, 0.365)
LINK_COMS = (
    (0.0, -0.02561, 0.00193),
    (0.2125, 0.0, 0.11336),
    (0.15, 0.0, 0.0265),
    (0.0, -0.0018, 0.01634),
    (0.0, 0.0018, 0.01634),
    (0.0, 0.0, -0.001159),
)

JOINT_NAMES = (
    "shoulder_pan",
    "shoulder_lift",
    "elbow",
    "wrist_1",
    "wrist_2",
    "wrist_3",
)
# Working range: +-360 deg on every joint but the elbow (+-180 deg, self-collision).
JOINT_LIMITS = (
    (-2 * np.pi, 2 * np.pi),
    (-2 * np.pi, 2 * np.pi),
    (-np.pi, np.pi),
    (-2 * np.pi, 2 * np.pi),
    (-2 * np.pi, 2 * np.pi),
    (-2 * np.pi, 2 * np.pi),
)
# Rated joint torques (N m): size-3 joints for the first three, size-1 for the wrists.
JOINT_TORQUE_LIMITS = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)
# Maximum joint speed (rad/s), 180 deg/s on every joint.
JOINT_SPEED_LIMIT = np.pi
# Position-servo stiffness (N m/rad) and damping (N m s/rad) per joint, tuned so the
# servo tracks a 10 Hz target stream like servoJ with its default gain. The damping is
# modelled as joint damping so that it stays stable when the torque saturates.
SERVO_KP = (4000.0, 4000.0, 3000.0, 800.0, 800.0, 500.0)
SERVO_KV = (200.0, 200.0, 150.0, 40.0, 40.0, 25.0)
# Radii of the collision capsules/cylinders per link (m).
LINK_RADII = (0.06, 0.054, 0.045, 0.038, 0.038, 0.032)

# Home pose: TCP 0.30 m above the table at (0.45, 0, 0.30), tool pointing down (yaw 0).
HOME_QPOS = (2.8409, -1.7068, 1.8578, -1.7217, -1.5708, -1.8715)


@dataclass(frozen=True)
class DHRobot:
    """Standard DH parameters of a serial arm; ``forward`` gives the flange pose."""

    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]

    def forward(self, q: np.ndarray) -> np.ndarray:
        """Return the 4x4 flange pose in the base frame for joint angles ``q`` (rad)."""
        pose = np.eye(4)
        for theta, d, a, alpha in zip(q, self.d, self.a, self.alpha, strict=True):
            pose = pose @ dh_transform(theta, d, a, alpha)
        return pose


UR5E_DH = DHRobot(DH_D, DH_A, DH_ALPHA)


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Standard DH link transform ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _fixed_link_transform(i: int) -> np.ndarray:
    """Transform from body ``link{i+1}`` (DH frame i rotated by theta) to DH frame i+1."""
    return dh_transform(0.0, DH_D[i], DH_A[i], DH_ALPHA[i])


def _quat_rx(angle: float) -> list[float]:
    return [float(np.cos(angle / 2)), float(np.sin(angle / 2)), 0.0, 0.0]


def _cylinder_inertia(mass: float, radius: float, length: float) -> list[float]:
    """Diagonal inertia of a solid cylinder along z."""
    side = mass * (3 * radius**2 + length**2) / 12.0
    return [side, side, 0.5 * mass * radius**2]


def add_ur5e(parent: mujoco.MjsBody, prefix: str = "") -> mujoco.MjsBody:
    """Add the UR5e arm under ``parent`` and return the flange body (DH frame 6).

    Joints are named ``{prefix}{JOINT_NAMES[i]}``, each driven by a position actuator of
    the same name; gravity on the arm links is compensated, as the UR controller does.
    """
    base = parent.add_body(name=f"{prefix}base")
    base.add_geom(
        name=f"{prefix}base_collision",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.075, 0.045, 0],
        pos=[0, 0, 0.045],
        rgba=[0.6, 0.62, 0.65, 1],
        contype=1,
        conaffinity=0,
    )
    body = base
    for i in range(6):
        link = body.add_body(name=f"{prefix}link{i + 1}")
        if i > 0:
            prev = _fixed_link_transform(i - 1)
            link.pos = prev[:3, 3].tolist()
            link.quat = _quat_rx(DH_ALPHA[i - 1])
        lo, hi = JOINT_LIMITS[i]
        link.add_joint(
            name=f"{prefix}{JOINT_NAMES[i]}",
            type=mujoco.mjtJoint.mjJNT_HINGE,
            axis=[0, 0, 1],
            range=[lo, hi],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            armature=0.1 if i < 3 else 0.02,
            damping=SERVO_KV[i],  # servo damping, integrated implicitly as joint damping
        )
        fixed = _fixed_link_transform(i)
        com = fixed[:3, :3] @ np.asarray(LINK_COMS[i]) + fixed[:3, 3]
        length = max(float(np.hypot(DH_A[i], DH_D[i])), 0.08)
        link.gravcomp = 1.0
        link.explicitinertial = True
        link.mass = LINK_MASSES[i]
        link.ipos = com.tolist()
        link.inertia = _cylinder_inertia(LINK_MASSES[i], LINK_RADII[i], length)
        _add_link_geoms(link, i, prefix)
        body = link
    flange = body.add_body(name=f"{prefix}flange")
    last = _fixed_link_transform(5)
    flange.pos = last[:3, 3].tolist()
    flange.quat = _quat_rx(DH_ALPHA[5])
    return flange


def _add_link_geoms(link: mujoco.MjsBody, i: int, prefix: str) -> None:
    """Capsules along the link's DH offsets: first along z by d, then along x by a."""
    radius = LINK_RADII[i]
    color = [0.25, 0.45, 0.75, 1] if i % 2 else [0.6, 0.62, 0.65, 1]
    d, a = DH_D[i], DH_A[i]
    start = 0.09 if i == 0 else 0.0  # link 1 starts above the fixed base housing
    segments = []
    if abs(d) > 1e-6:
        segments.append([0, 0, start, 0, 0, d])
    if abs(a) > 1e-6:
        segments.append([0, 0, d, a, 0, d])
    for k, fromto in enumerate(segments):
        link.add_geom(
            name=f"{prefix}link{i + 1}_{k}",
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=fromto,
            size=[radius, 0, 0],
            rgba=color,
            contype=1,
            conaffinity=0,
        )
