"""Opening a cell's devices from its cell file: the arm with its gripper and cameras."""

from __future__ import annotations

from twinrl_robot.cell_file import CellFile
from twinrl_robot.errors import RobotError
from twinrl_robot.robot import Privileged
from twinrl_robot.ur.cameras import Camera, CameraRig, OpenCVCamera, RealSenseCamera
from twinrl_robot.ur.driver import Arrange, URArm
from twinrl_robot.ur.gripper import DigitalGripper, Gripper, NoGripper, RobotiqGripper
from twinrl_sim.tasks import Task


def open_gripper(cell: CellFile) -> Gripper:
    spec = cell.gripper
    if spec.kind.startswith("robotiq"):
        return RobotiqGripper(cell.arm.host, port=spec.port, kind=spec.kind)
    if spec.kind == "digital":
        import rtde_io

        try:
            io = rtde_io.RTDEIOInterface(cell.arm.host)
        except RuntimeError as err:
            raise RobotError(
                f"cannot open the controller's I/O at {cell.arm.host} for the gripper: {err}"
            ) from None
        return DigitalGripper(io, spec.output)
    return NoGripper()


def open_cameras(cell: CellFile, names: tuple[str, ...] | None = None) -> CameraRig:
    """The cell's cameras (those in ``names``, all by default), each streaming."""
    known = {c.name: c for c in cell.cameras}
    wanted = list(known) if names is None else list(names)
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise RobotError(f"camera(s) {unknown} are not in the cell file, which has {list(known)}")
    cameras: list[Camera] = []
    try:
        for name in wanted:
            spec = known[name]
            kind = OpenCVCamera if spec.kind == "opencv" else RealSenseCamera
            cameras.append(kind(spec.name, spec.source, spec.width, spec.height, spec.fps))
    except RobotError:
        for camera in cameras:
            camera.close()
        raise
    return CameraRig(cameras)


def open_arm(
    cell: CellFile,
    task: Task,
    *,
    cameras: tuple[str, ...] = (),
    effort: bool = True,
    arrange: Arrange | None = None,
    privileged: Privileged | None = None,
) -> URArm:
    """The cell's arm with its gripper and the named cameras (the arm is reached first,
    so an unreachable controller is named as such)."""
    arm = URArm(cell, task, arrange=arrange, effort=effort, privileged=privileged)
    try:
        arm.gripper = open_gripper(cell)
        arm.cameras = open_cameras(cell, cameras)
    except RobotError:
        arm.close()
        raise
    return arm
