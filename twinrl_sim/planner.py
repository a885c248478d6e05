"""Planner-based demonstration synthesis: grasp, collision-free waypoints, 10 Hz actions.

For a configuration: sample antipodal grasps ``T_grasp`` on the object; the TCP poses
are ``T_start = T0 * T_grasp`` (pick-up) and ``T_end = T_target * T_grasp`` for every
goal pose of the task (placement, or the wiping path). The waypoints approach / grasp /
lift / transport / place (or wipe) / retreat are checked for collisions with MuJoCo
contacts (arm, gripper and held object against the table and fixtures); the transport
height is raised until the path is clear, and grasps whose path cannot be cleared are
dropped. The path is then time-parameterised with a trapezoidal speed profile into the
episode contract's 10 Hz end-effector deltas, ready to execute in the twin.

A *detour* demo first strays from home to a random point beside the object and does the
task from there: views from off the straight path, and the way back to the object, for
an image policy that would otherwise only ever see the path its demos took.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from twinrl_sim.body_tree import subtree
from twinrl_sim.build import yaw_quat
from twinrl_sim.cell import Cell
from twinrl_sim.control import MAX_ROTATION, TRACKED_ROTATION, quat_conj, quat_mul, quat_to_rotvec
from twinrl_sim.grasping import Grasp, sample_antipodal_grasps
from twinrl_sim.layout import MOUNT_BODY
from twinrl_sim.planar import yaw_of
from twinrl_sim.robots import gripper as gripper_lib
from twinrl_sim.tasks.base import Task, TaskConfig
from twinrl_sim.tasks.expert import grasp_yaw, nearest_equivalent, tool_quat

TRANSPORT_HEIGHTS = (0.10, 0.18, 0.28)  # m above the higher of pick-up and goal
EASE_PEAK = 1.5  # peak rate of the speed profile's ease over its mean
APPROACH = 0.08  # m: straight vertical approach and retreat
CHECK_SPACING = 0.01  # m between collision checks along a segment
PENETRATION = 0.001  # m: deeper contacts count as collisions
# Where a detour strays: this far from the object in the table plane (an image policy that
# had lost the banana was 10-20 cm from it), this much above the approach height, turned
# this far from home; a few draws until its path is clear.
DETOUR_RADIUS = (0.08, 0.20)  # m
DETOUR_RISE = (0.0, 0.12)  # m
DETOUR_TURN = 0.4  # rad
DETOUR_DRAWS = 8
# Where a missed grasp closes: this far above the grasp (the image policy's misses closed
# 1.3-1.7 cm high), then it lifts this much empty-handed and opens before grasping again.
MISS_HEIGHT = (0.02, 0.045)  # m
MISS_LIFT = 0.03  # m


@dataclass(frozen=True)
class Waypoint:
    position: np.ndarray
    yaw: float
    gripper: float
    speed: float  # m/s along the segment that ends here
    dwell: int = 0  # control steps to hold here (gripper closing/opening)


@dataclass
class PlannerSettings:
    """Speeds (m/s), acceleration (m/s^2) and how many grasps to try."""

    speed: float = 0.3
    slow_speed: float = 0.08
    acceleration: float = 1.0
    # Peak turning rate (rad/s); None: what the wrist follows (TRACKED_ROTATION a step).
    max_yaw_rate: float | None = None
    grasps_to_try: int = 8
    grasp_samples: int = 200
    close_steps: int = 5
    open_steps: int = 4
    settle_steps: int = 3


@dataclass
class Plan:
    """A synthesized demonstration: actions at the control rate and how they were made."""

    actions: np.ndarray  # (T, 7) float32, episode-contract deltas
    grasp: Grasp
    transport_height: float
    waypoints: list[Waypoint] = field(default_factory=list)


class CollisionChecker:
    """Poses the arm (by IK) and the held object in a scratch copy of the cell and asks
    MuJoCo for contacts between robot or held object and everything else."""

    def __init__(self, cell: Cell, object_name: str) -> None:
        self.cell = cell
        self.model = cell.model
        self.data = mujoco.MjData(cell.model)
        mujoco.mj_copyData(self.data, cell.model, cell.data)
        robot_root = self.model.body(MOUNT_BODY).id
        self.robot_bodies = subtree(self.model, robot_root)
        self.object_body = self.model.body(object_name).id
        self.object_qpos = self.model.joint(f"{object_name}_free").qposadr[0]
        self.pads = {self.model.geom(f"gripper_pad_{side}").id for side in ("left", "right")}
        self.q = cell.arm_q

    def collides(
        self, position: np.ndarray, yaw: float, holding: Grasp | None, opening: float
    ) -> bool:
        """Whether the robot at this TCP pose (and the object, if held) touches anything."""
        controller = self.cell.controller
        quat = tool_quat(yaw)
        self.q = controller.solve_pose(position, quat, self.q, iterations=30)
        data = self.data
        data.qpos[self.cell.arm_qpos] = self.q
        if self.cell.gripper_qpos is not None:
            finger = gripper_lib.STROKE - opening / 2
            data.qpos[self.cell.gripper_qpos] = finger
            data.qpos[self.model.joint(gripper_lib.MIRROR_JOINT).qposadr[0]] = finger
        if holding is not None:
            object_pos, object_quat = object_pose_from_tcp(position, yaw, holding)
            data.qpos[self.object_qpos : self.object_qpos + 3] = object_pos
            data.qpos[self.object_qpos + 3 : self.object_qpos + 7] = object_quat
        mujoco.mj_kinematics(self.model, data)
        mujoco.mj_collision(self.model, data)
        reached, _ = controller.forward(self.q)
        if np.linalg.norm(reached - position) > 0.005:
            return True  # out of reach counts as blocked
        for contact in data.contact[: data.ncon]:
            if contact.dist > -PENETRATION:
                continue
            b1, b2 = self.model.geom_bodyid[contact.geom1], self.model.geom_bodyid[contact.geom2]
            moving = {
                b for b in (b1, b2) if b in self.robot_bodies or (holding and b == self.object_body)
            }
            if not moving:
                continue
            if holding and {b1, b2} <= self.robot_bodies | {self.object_body}:
                continue  # the gripper squeezing the object it holds
            return True
        return False


def object_pose_from_tcp(
    tcp: np.ndarray, tool_yaw: float, grasp: Grasp
) -> tuple[np.ndarray, np.ndarray]:
    """Object body pose for a TCP pose when held with ``grasp`` (inverse of T_grasp)."""
    object_yaw = tool_yaw - grasp.yaw
    c, s = math.cos(object_yaw), math.sin(object_yaw)
    offset = np.array(
        [
            c * grasp.position[0] - s * grasp.position[1],
            s * grasp.position[0] + c * grasp.position[1],
            grasp.position[2],
        ]
    )
    return tcp - offset, yaw_quat(object_yaw)


def tcp_from_object(
    object_pos: np.ndarray, object_yaw: float, grasp: Grasp
) -> tuple[np.ndarray, float]:
    """TCP pose for an object pose: ``T_object * T_grasp``."""
    c, s = math.cos(object_yaw), math.sin(object_yaw)
    p = grasp.position
    return object_pos + np.array(
        [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]]
    ), object_yaw + grasp.yaw


def _segment_clear(
    checker: CollisionChecker,
    a: np.ndarray,
    ya: float,
    b: np.ndarray,
    yb: float,
    holding: Grasp | None,
    opening: float,
    skip_end: float = 0.0,
) -> bool:
    length = float(np.linalg.norm(b - a))
    count = max(2, int(length / CHECK_SPACING) + 1)
    for s in np.linspace(0.0, 1.0, count):
        if length * (1 - s) < skip_end:
            break
        if checker.collides(a + s * (b - a), ya + s * (yb - ya), holding, opening):
            return False
    return True


def plan_demo(
    task: Task,
    cell: Cell,
    config: TaskConfig,
    rng: np.random.Generator,
    settings: PlannerSettings | None = None,
    detour: np.random.Generator | None = None,
    miss: np.random.Generator | None = None,
    closed_detour: bool = False,
) -> Plan | None:
    """Plan a demonstration for ``config`` (the cell is reset to it); ``None`` if no
    grasp admits a collision-free path. With ``detour`` (the generator that draws it),
    the arm first strays to a point beside the object (see :func:`detour_waypoint`);
    with ``closed_detour`` too, it strays with the fingers closed and opens them on the
    way back: closed fingers holding nothing, away from the object.
    With ``miss``, the first grasp closes :data:`MISS_HEIGHT` above the object, lifts
    empty-handed, opens and grasps again: what closed fingers holding nothing look like,
    and the recovery from it."""
    settings = settings or PlannerSettings()
    task.start(cell, config)
    home, home_quat = cell.tcp_pose()
    home_yaw = yaw_of(home_quat)
    object_pos, _ = cell.object_pose(task.object_name)
    object_yaw = config.object[2]
    goals = task.goal_poses(cell, config)
    # Grasp near the task's nominal grasp yaw, as the scripted expert does: the one
    # nearest home decides which way the wrist turns. Ranking by the turn from home alone
    # let a grasp 20 deg off a curved banana's heading turn the other way, so that demos
    # of neighbouring configurations disagreed and a policy imitating both stopped halfway.
    nominal_yaw = grasp_yaw(object_yaw, task.grasp_period, task.grasp_yaw_offset, home_yaw)
    grasps = sample_antipodal_grasps(
        cell, task.object_name, rng, samples=settings.grasp_samples, reference_yaw=nominal_yaw
    )
    up = np.array([0.0, 0.0, APPROACH])
    for candidate in grasps[: settings.grasps_to_try]:
        # The gripper is symmetric under a half turn: the equivalent nearest the nominal.
        start_yaw = nearest_equivalent(object_yaw + candidate.yaw, math.pi, nominal_yaw)
        grasp = _grasp_with_yaw(candidate, start_yaw - object_yaw)
        start, _ = tcp_from_object(object_pos, object_yaw, grasp)
        ends = [tcp_from_object(pos, yaw, grasp) for pos, yaw in goals]
        checker = CollisionChecker(cell, task.object_name)
        if not _segment_clear(
            checker, start + up, start_yaw, start, start_yaw, None, 2 * gripper_lib.STROKE
        ):
            continue
        for height in TRANSPORT_HEIGHTS:
            top = max(start[2], *(p[2] for p, _ in ends)) + height
            lift = np.array([start[0], start[1], top])
            above = np.array([ends[0][0][0], ends[0][0][1], top])
            lifted = start + [0.0, 0.0, 0.02]  # clear of the table contact it starts in
            if (
                _segment_clear(checker, lifted, start_yaw, lift, start_yaw, grasp, grasp.width)
                and _segment_clear(checker, lift, start_yaw, above, ends[0][1], grasp, grasp.width)
                and _segment_clear(
                    checker,
                    above,
                    ends[0][1],
                    ends[0][0],
                    ends[0][1],
                    grasp,
                    grasp.width,
                    skip_end=0.003,
                )
            ):
                break
        else:
            continue
        waypoints = []
        if detour is not None:
            stray = detour_waypoint(
                checker, (home, home_yaw), (start + up, start_yaw), object_pos, detour, settings
            )
            if stray is None:
                continue
            if closed_detour:
                stray = replace(stray, gripper=1.0, dwell=settings.close_steps)
            waypoints.append(stray)
        waypoints.append(Waypoint(start + up, start_yaw, 0.0, settings.speed))
        if miss is not None:
            high = start + [0.0, 0.0, miss.uniform(*MISS_HEIGHT)]
            empty = high + [0.0, 0.0, MISS_LIFT]
            waypoints += [
                Waypoint(high, start_yaw, 0.0, settings.slow_speed),
                Waypoint(high, start_yaw, 1.0, settings.slow_speed, dwell=settings.close_steps),
                Waypoint(empty, start_yaw, 1.0, settings.slow_speed),
                Waypoint(empty, start_yaw, 0.0, settings.slow_speed, dwell=settings.open_steps),
            ]
        waypoints += [
            Waypoint(start, start_yaw, 0.0, settings.slow_speed),
            Waypoint(start, start_yaw, 1.0, settings.slow_speed, dwell=settings.close_steps),
            Waypoint(lift, start_yaw, 1.0, settings.speed),
            Waypoint(above, ends[0][1], 1.0, settings.speed),
            Waypoint(ends[0][0], ends[0][1], 1.0, settings.slow_speed),
        ]
        for pos, yaw in ends[1:]:
            waypoints.append(Waypoint(pos, yaw, 1.0, settings.slow_speed * 2))
        if task.releases_object:
            last_pos, last_yaw = ends[-1]
            waypoints.append(
                Waypoint(last_pos, last_yaw, 0.0, settings.slow_speed, dwell=settings.open_steps)
            )
            waypoints.append(
                Waypoint(last_pos + up, last_yaw, 0.0, settings.speed, dwell=settings.settle_steps)
            )
        else:
            last_pos, last_yaw = ends[-1]
            waypoints.append(
                Waypoint(last_pos + up, last_yaw, 1.0, settings.speed, dwell=settings.settle_steps)
            )
        actions = time_parameterize(home, home_yaw, waypoints, cell.control_dt, settings)
        return Plan(actions=actions, grasp=grasp, transport_height=height, waypoints=waypoints)
    return None


def detour_waypoint(
    checker: CollisionChecker,
    home: tuple[np.ndarray, float],
    approach: tuple[np.ndarray, float],
    object_pos: np.ndarray,
    rng: np.random.Generator,
    settings: PlannerSettings,
) -> Waypoint | None:
    """A point to stray to, open-handed, on the way from ``home`` to the ``approach``
    pose (TCP position, yaw): :data:`DETOUR_RADIUS` from the object, above the approach
    height, both legs clear of the table and fixtures; ``None`` if no draw is clear."""
    opening = 2 * gripper_lib.STROKE
    for _ in range(DETOUR_DRAWS):
        angle = rng.uniform(0.0, 2 * math.pi)
        radius = rng.uniform(*DETOUR_RADIUS)
        point = np.array(
            [
                object_pos[0] + radius * math.cos(angle),
                object_pos[1] + radius * math.sin(angle),
                approach[0][2] + rng.uniform(*DETOUR_RISE),
            ]
        )
        yaw = home[1] + rng.uniform(-DETOUR_TURN, DETOUR_TURN)
        if _segment_clear(checker, *home, point, yaw, None, opening) and _segment_clear(
            checker, point, yaw, *approach, None, opening
        ):
            return Waypoint(point, yaw, 0.0, settings.speed)
    return None


def _grasp_with_yaw(grasp: Grasp, yaw: float) -> Grasp:
    """The same grasp with its relative yaw replaced (a half-turn equivalent)."""
    return Grasp(grasp.position, yaw, grasp.width, grasp.quality, grasp.score)


def time_parameterize(
    start: np.ndarray,
    start_yaw: float,
    waypoints: list[Waypoint],
    dt: float,
    settings: PlannerSettings,
) -> np.ndarray:
    """10 Hz end-effector deltas through ``waypoints`` with a trapezoidal speed profile."""
    yaw_rate = TRACKED_ROTATION / dt if settings.max_yaw_rate is None else settings.max_yaw_rate
    poses = [(np.asarray(start, float), start_yaw, 0.0)]
    for wp in waypoints:
        a, ya, _ = poses[-1]
        distance = float(np.linalg.norm(wp.position - a))
        turn = abs(wp.yaw - ya)
        duration = max(
            _trapezoid_time(distance, wp.speed, settings.acceleration),
            EASE_PEAK * turn / yaw_rate,
        )
        steps = max(1, math.ceil(duration / dt))
        for k in range(1, steps + 1):
            s = _trapezoid_fraction(k / steps)
            poses.append((a + s * (wp.position - a), ya + s * (wp.yaw - ya), wp.gripper))
        poses.extend([(wp.position.copy(), wp.yaw, wp.gripper)] * wp.dwell)
    actions = []
    for (p0, y0, _), (p1, y1, g1) in itertools.pairwise(poses):
        rot = quat_to_rotvec(quat_mul(tool_quat(y1), quat_conj(tool_quat(y0))))
        angle = float(np.linalg.norm(rot))
        if angle > MAX_ROTATION:
            rot *= MAX_ROTATION / angle
        actions.append(np.concatenate([p1 - p0, rot, [g1]]))
    return np.asarray(actions, np.float32)


def _trapezoid_time(distance: float, speed: float, acceleration: float) -> float:
    if distance <= speed**2 / acceleration:
        return 2.0 * math.sqrt(distance / acceleration)
    return distance / speed + speed / acceleration


def _trapezoid_fraction(u: float) -> float:
    """Smooth 0..1 progress (cubic ease in/out) standing in for the trapezoid's shape;
    its rate peaks at ``EASE_PEAK`` times the mean."""
    return u * u * (3.0 - 2.0 * u)
