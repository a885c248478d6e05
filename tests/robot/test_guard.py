"""The joint guard between every action source and a real arm: whatever the source asks,
no joint target leaves the joint limits, the speed and acceleration limits, the
workspace box, the tool cone or the table's clearance; an unsafe start is refused."""

from __future__ import annotations

from types import SimpleNamespace
from typing import ClassVar

import mujoco
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from twinrl_robot.cell_file import SafetySpec
from twinrl_robot.guard import BOX_TOLERANCE, GuardLimits, JointGuard, UnsafeStart, tool_tilt_deg
from twinrl_robot.tool_clearance import tool_points
from twinrl_robot.wrappers.safety import SafetyLimits
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.control import EndEffectorController, IKSettings
from twinrl_sim.tasks import make_task

CONTROL_HZ = 10.0
SAFETY = SafetySpec(tool_cone_deg=30.0, max_joint_speed=1.0, max_joint_acceleration=4.0)


@pytest.fixture(scope="module")
def twin() -> Cell:
    return Cell(compile_scene(make_task("pick_place").scene))


def _guard(twin: Cell) -> tuple[JointGuard, EndEffectorController]:
    ws = SAFETY.workspace
    box = (np.array(ws.low), np.array(ws.high))
    ik = EndEffectorController(
        twin.model,
        twin.layout,
        box,
        1.0 / CONTROL_HZ,
        IKSettings(joint_margin=SAFETY.joint_margin, max_joint_speed=SAFETY.max_joint_speed),
    )
    limits = GuardLimits(
        q_low=ik.q_low,
        q_high=ik.q_high,
        max_speed=SAFETY.max_joint_speed,
        max_acceleration=SAFETY.max_joint_acceleration,
        box_low=box[0],
        box_high=box[1],
        cone_deg=SAFETY.tool_cone_deg,
        tool_points=tool_points(twin),
        table_top=twin.table_top,
        table_clearance=SAFETY.table_clearance,
        approach_height=SAFETY.table_approach_height,
        approach_speed=SAFETY.table_approach_speed,
    )
    return JointGuard(limits, ik.forward, 1.0 / CONTROL_HZ), ik


def _assert_safe(guard: JointGuard, targets: list[np.ndarray]) -> None:
    lim, dt = guard.limits, guard.period
    q = np.array(targets)
    assert (q >= lim.q_low - 1e-9).all() and (q <= lim.q_high + 1e-9).all()
    velocity = np.diff(q, axis=0) / dt
    assert np.abs(velocity).max(initial=0.0) <= lim.max_speed + 1e-6
    assert np.abs(np.diff(velocity, axis=0) / dt).max(initial=0.0) <= lim.max_acceleration + 1e-6
    for target in q:
        position, quat = guard.kinematics(target)
        assert (position >= lim.box_low - BOX_TOLERANCE).all()
        assert (position <= lim.box_high + BOX_TOLERANCE).all()
        assert tool_tilt_deg(quat) <= lim.cone_deg + 1e-6
    heights = np.array([_lowest_tool_point(guard, target) for target in q])
    assert heights.min(initial=np.inf) >= lim.table_clearance - BOX_TOLERANCE
    near = heights[1:] < lim.table_clearance + lim.approach_height
    descent = -np.diff(heights) / dt
    assert descent[near].max(initial=0.0) <= lim.approach_speed + 1e-6


def _lowest_tool_point(guard: JointGuard, q: np.ndarray) -> float:
    """Height (m) above the table of the tool's lowest corner at joint positions ``q``."""
    position, quat = guard.kinematics(q)
    w, x, y, z = quat
    z_row = np.array([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])
    return float(position[2] + (guard.limits.tool_points @ z_row).min() - guard.limits.table_top)


actions = st.lists(st.lists(st.floats(-1.0, 1.0), min_size=7, max_size=7), min_size=1, max_size=40)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(sequence=actions)
def test_no_action_sequence_leaves_the_limits(twin: Cell, sequence: list[list[float]]) -> None:
    """Random actions (far beyond the per-step limits) through the action clipping, the
    twin's IK and the guard: every target the arm would get keeps every limit."""
    guard, ik = _guard(twin)
    home = np.array(twin.layout.home_qpos)
    guard.reset(home)
    ik.reset(home)
    clip = SafetyLimits(_NullRobot(), SAFETY.max_step_translation, SAFETY.max_step_rotation)
    measured, sent = home, [home]
    for raw in sequence:
        action = clip.action(np.array(raw, np.float32) * 0.3)
        assert np.linalg.norm(action[:3]) <= SAFETY.max_step_translation + 1e-6
        assert np.linalg.norm(action[3:6]) <= SAFETY.max_step_rotation + 1e-6
        guarded = guard(ik.joint_targets(action, measured))
        ik.q_target = guarded.q.copy()
        measured = guarded.q  # an arm that tracks perfectly: the hardest case for the box
        sent.append(guarded.q)
    _assert_safe(guard, sent)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    steps=st.lists(st.lists(st.floats(-0.6, 0.6), min_size=6, max_size=6), min_size=1, max_size=30)
)
# Once sent 30.09 deg from straight down: the braking was checked on a line in joint
# space, and the next period's target lay off it.
@example(
    steps=[[0, 0.15625, 0.5, 0, 0, 0], [0, 0, 0, 0.59375, 0, 0], [0, 0, 0, 0.0625, 0, 0],
           [0] * 6, [0, 0, 0, -0.125, 0.5, 0], [0, -0.5, 0, -0.5, 0, 0], [0] * 6]
)  # fmt: skip
def test_no_joint_target_sequence_leaves_the_limits(twin: Cell, steps: list[list[float]]) -> None:
    """Replay and excitation send joint targets directly: random jumps of up to 0.6 rad
    per joint per step are clipped to every limit too."""
    guard, _ = _guard(twin)
    q = np.array(twin.layout.home_qpos)
    guard.reset(q)
    sent = [q]
    for jump in steps:
        q = q + np.array(jump)
        sent.append(guard(q).q)
    _assert_safe(guard, sent)


def test_a_start_outside_the_limits_is_refused_and_says_why(twin: Cell) -> None:
    guard, ik = _guard(twin)
    home = np.array(twin.layout.home_qpos)
    guard.check_start(home)  # the twin's home stands inside
    position, quat = ik.forward(home)
    low = ik.solve_pose(position + np.array([0, 0, -0.31]), quat, home)  # below the table
    with pytest.raises(UnsafeStart, match="outside the box in z"):
        guard.check_start(low)
    with pytest.raises(UnsafeStart, match="joint 3 beyond its limit"):
        guard.check_start(home + np.array([0, 0, 10.0, 0, 0, 0]))


def test_clipping_reports_what_it_clipped(twin: Cell) -> None:
    guard, _ = _guard(twin)
    home = np.array(twin.layout.home_qpos)
    guard.reset(home)
    assert guard(home).clipped == ()
    fast = guard(home + 0.5)
    assert "joint speed" in fast.clipped
    assert np.abs(fast.q - home).max() <= SAFETY.max_joint_acceleration * 0.01 + 1e-9


def test_a_tilted_tool_pushed_into_the_table_keeps_its_fingers_clear(twin: Cell) -> None:
    """Once a protective stop on the emulated arm: the box let the TCP down to 5 mm at
    0.2 m/s, and an open finger's corner, 3 mm under the TCP and lower still at a 3 deg
    tilt, struck the table at 168 N. Every corner of the tool now keeps the clearance, at
    any tilt, and nears it at the approach speed."""
    guard, ik = _guard(twin)
    home = np.array(twin.layout.home_qpos)
    position, quat = ik.forward(home)
    for tilt_deg in (0.0, 3.0, 10.0):
        tilt, tilted = np.zeros(4), np.zeros(4)
        mujoco.mju_axisAngle2Quat(tilt, np.array([1.0, 0.0, 0.0]), np.radians(tilt_deg))
        mujoco.mju_mulQuat(tilted, tilt, quat)  # tilted about the base's x axis
        start = ik.solve_pose(position, tilted, home)
        guard.reset(start)
        q, sent = start, [start]
        for _ in range(40):  # straight down, far into the table
            q = guard(ik.solve_pose(ik.forward(q)[0] - np.array([0, 0, 0.05]), tilted, q)).q
            sent.append(q)
        _assert_safe(guard, sent)
        # Held at the clearance, not short of it.
        assert _lowest_tool_point(guard, sent[-1]) < SAFETY.table_clearance + 0.002, tilt_deg


class _NullRobot:
    """Stands under an action wrapper whose clipping alone is tested."""

    control_hz = CONTROL_HZ
    world = "twin"
    names: ClassVar[dict] = {}
    privileged = None


def test_a_replay_that_starts_outside_the_box_is_refused(twin: Cell) -> None:
    from twinrl_data.schema import Episode, EpisodeMeta
    from twinrl_robot.replay_source import ReplaySource, check_replay_start

    guard, ik = _guard(twin)
    home = np.array(twin.layout.home_qpos)
    position, quat = ik.forward(home)
    below = ik.solve_pose(position + np.array([0, 0, -0.31]), quat, home)
    steps = 3
    episode = Episode(
        EpisodeMeta(task="pick_place", source="teleop", world="real"),
        {
            "observation.state": np.zeros((steps, 20), np.float32),
            "action": np.zeros((steps, 7), np.float32),
            "command.joint_target": np.tile(below, (steps, 1)).astype(np.float32),
        },
    )
    arm = SimpleNamespace(guard=guard)  # what the check reads of a real arm
    with pytest.raises(UnsafeStart, match="the replay's start pose is outside"):
        check_replay_start(arm, ReplaySource(episode))
