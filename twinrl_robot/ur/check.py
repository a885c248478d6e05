"""``twinrl robot check``: connect to a cell and measure what matters before recording.

It reports the controller (PolyScope version, robot and safety modes, remote control),
runs the servo stream holding the arm where it stands for a few seconds and measures
its period (the control loop's real rate and jitter), measures each camera's frame rate
and frame age, reads the gripper, and checks the arm's pose against the safety limits.
The safety box, the arm's pose and the tool's path are written to a Rerun recording.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinrl_robot.cell_file import CellFile
from twinrl_robot.ur.driver import RobotConnectionError, URArm, require_reachable
from twinrl_robot.ur.hardware import open_arm
from twinrl_sim.body_tree import ancestors
from twinrl_sim.layout import MOUNT_BODY
from twinrl_sim.tasks import Task


@dataclass(frozen=True)
class CameraCheck:
    name: str
    fps: float
    age_ms_p50: float  # frame age when a control step takes it
    dropped: int


@dataclass(frozen=True)
class CellCheck:
    """What :func:`check_cell` found."""

    controller: str
    robot_mode: str
    safety_mode: str
    remote_control: bool
    servo_hz: float
    period_ms: tuple[float, float, float]  # p50, p99, max of the servo stream's period
    gripper: str
    gripper_opening: float
    pose_problem: str  # "" when the arm stands inside the safety limits
    cameras: list[CameraCheck] = field(default_factory=list)
    recording: Path | None = None


def check_cell(
    cell: CellFile, task: Task, *, seconds: float = 2.0, rerun: Path | None = None
) -> CellCheck:
    """Connect to ``cell`` and measure it for ``seconds`` (see the module docstring)."""
    import dashboard_client

    require_reachable(cell.arm.host)
    dashboard = dashboard_client.DashboardClient(cell.arm.host)
    try:
        dashboard.connect()
    except RuntimeError as err:
        raise RobotConnectionError(
            f"the UR controller's dashboard at {cell.arm.host}:29999 does not answer ({err}); "
            "check that the controller has finished booting"
        ) from None
    try:
        controller = dashboard.polyscopeVersion()
        robot_mode, safety_mode = dashboard.robotmode(), dashboard.safetystatus()
        remote = bool(dashboard.isInRemoteControl())
    finally:
        dashboard.disconnect()
    arm = open_arm(cell, task, cameras=tuple(c.name for c in cell.cameras))
    try:
        q = np.array(arm.measured_q(), float)
        problem = arm.guard.violation(q)
        arm.stream.start(q)
        deadline = time.monotonic() + seconds
        path = []
        while time.monotonic() < deadline:
            if arm.cameras.cameras:
                arm.cameras.images()
            path.append(arm.kinematics.forward(arm.measured_q())[0])
            time.sleep(1.0 / cell.arm.control_hz)
        arm.stream.stop()
        periods = np.array(arm.stream.periods[1:]) * 1000.0
        cameras = [
            CameraCheck(
                c.name,
                c.stats.fps,
                float(np.median(c.stats.latencies) * 1000.0) if c.stats.latencies else 0.0,
                c.stats.dropped,
            )
            for c in arm.cameras.cameras
        ]
        report = CellCheck(
            controller=controller,
            robot_mode=robot_mode.removeprefix("Robotmode: "),
            safety_mode=safety_mode.removeprefix("Safetystatus: "),
            remote_control=remote,
            servo_hz=cell.arm.servo_rate,
            period_ms=(
                float(np.percentile(periods, 50)),
                float(np.percentile(periods, 99)),
                float(periods.max()),
            ),
            gripper=arm.gripper.describe(),
            gripper_opening=arm.gripper.opening(),
            pose_problem=problem,
            cameras=cameras,
            recording=rerun,
        )
        if rerun is not None:
            _record(rerun, cell, arm, q, np.array(path))
        return report
    finally:
        arm.close()


def _record(path: Path, cell: CellFile, arm: URArm, q: np.ndarray, tool_path: np.ndarray) -> None:
    """The safety box, the arm's links and the tool's path in a Rerun recording."""
    import mujoco
    import rerun as rr

    recording = rr.RecordingStream("twinrl.robot_check")
    recording.save(str(path))
    box = cell.safety.workspace
    low, high = np.array(box.low), np.array(box.high)
    recording.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    recording.log(
        "world/safety_box",
        rr.Boxes3D(
            centers=[(low + high) / 2], half_sizes=[(high - low) / 2], labels=["safety box"]
        ),
        static=True,
    )
    twin = arm.twin
    twin.data.qpos[twin.arm_qpos] = q
    mujoco.mj_kinematics(twin.model, twin.data)
    chain = [twin.model.body(MOUNT_BODY).id]
    flange = twin.model.body(twin.layout.flange_body).id
    chain += sorted(ancestors(twin.model, flange) - set(chain))
    recording.log("world/arm", rr.LineStrips3D([twin.data.xpos[chain]]), static=True)
    if len(tool_path):
        recording.log("world/tool_path", rr.Points3D(tool_path, radii=0.004), static=True)
    recording.flush()
    recording.disconnect()
