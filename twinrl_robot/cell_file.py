"""A real cell's file: how to reach the arm, its gripper and cameras, the safety limits
between every action source and the arm, and which twin the cell corresponds to.

::

    name: lab_ur5e
    twin: pick_place                  # a built-in cell or a scene spec file
    arm:
      model: ur5e                     # ur3e ur5e ur10e ur16e (e-Series), ur3 ur5 ur10 (CB3)
      host: 192.168.1.10
      control_hz: 10                  # the episode's control rate
      servo_hz: 500                   # the controller's: 500 (e-Series) or 125 (CB3)
      servo: servoj                   # servoj (the twin's IK, as the twin does) or servol
      tcp_offset: [0, 0, 0.15, 0, 0, 0]   # the TCP set on the controller: m, axis-angle rad
      payload: {mass: 0.9, cog: [0, 0, 0.05]}
      realtime_priority: 80           # optional (Linux): SCHED_FIFO for the robot loop's thread
    gripper: {kind: robotiq_2f85, port: 63352}   # robotiq_2f85 robotiq_2f140 digital none
    cameras:
      - {name: front, kind: opencv, source: "0", width: 640, height: 480, fps: 30}
      - {name: wrist, kind: realsense, source: "123456789", width: 640, height: 480, fps: 30}
    safety:
      workspace: {low: [0.15, -0.55, 0.005], high: [0.85, 0.55, 0.6]}   # base frame, m
      tool_cone_deg: 45               # the tool axis within this angle of straight down
      max_step_translation: 0.02      # m per control step
      max_step_rotation: 0.1          # rad per control step
      joint_margin: 0.05              # rad kept from each joint's limits
      max_joint_speed: 1.0            # rad/s
      max_joint_acceleration: 4.0     # rad/s^2
      watchdog_ms: 100                # the arm stops when no command came for this long
    teleop:                           # optional: each device's scaling, axes, buttons
      spacemouse: {translation: 0.02, deadband: 0.1, axes: [y, -x, z, pitch, -roll, yaw]}

Validated like scene specs: every number finite and within physical bounds, unknown
keys named with the nearest valid one, every problem in one line.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from twinrl_robot.errors import RobotError
from twinrl_robot.teleop.settings import TeleopSpec
from twinrl_sim.spec import WorkspaceSpec, read_yaml, validate_model

ARM_MODELS = {
    "ur3e": 500.0,
    "ur5e": 500.0,
    "ur10e": 500.0,
    "ur16e": 500.0,
    "ur3": 125.0,
    "ur5": 125.0,
    "ur10": 125.0,
}  # model -> its controller's servo rate (Hz)
Metre = Annotated[float, Field(allow_inf_nan=False, ge=-5.0, le=5.0)]
Radian = Annotated[float, Field(allow_inf_nan=False, ge=-7.0, le=7.0)]


class CellFileError(RobotError):
    """A cell file is invalid; the message says where and why."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PayloadSpec(_Strict):
    mass: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=50.0)] = 0.0  # kg
    cog: tuple[Metre, Metre, Metre] = (0.0, 0.0, 0.0)  # m, flange frame


class ArmSpec(_Strict):
    model: Literal["ur3e", "ur5e", "ur10e", "ur16e", "ur3", "ur5", "ur10"] = "ur5e"
    host: str
    control_hz: Annotated[float, Field(allow_inf_nan=False, ge=1.0, le=100.0)] = 10.0
    servo_hz: Annotated[float, Field(allow_inf_nan=False, ge=100.0, le=1000.0)] | None = None
    servo: Literal["servoj", "servol"] = "servoj"
    tcp_offset: tuple[Metre, Metre, Metre, Radian, Radian, Radian] = (0, 0, 0, 0, 0, 0)
    payload: PayloadSpec = PayloadSpec()
    # SCHED_FIFO priority of the robot loop's thread (twinrl_robot.realtime); None: the
    # normal policy.
    realtime_priority: Annotated[int, Field(ge=1, le=99)] | None = None

    @field_validator("host")
    @classmethod
    def _address(cls, host: str) -> str:
        try:
            ipaddress.ip_address(host)
        except ValueError:
            if not host or any(c.isspace() for c in host) or len(host) > 253:
                raise ValueError("must be an IP address or a host name") from None
        return host

    @property
    def servo_rate(self) -> float:
        """The controller's servo rate: as given, or the model's."""
        return self.servo_hz or ARM_MODELS[self.model]

    @model_validator(mode="after")
    def _rates(self) -> ArmSpec:
        if self.servo_hz is not None and self.servo_hz > ARM_MODELS[self.model] + 1e-9:
            raise ValueError(
                f"a {self.model} servos at {ARM_MODELS[self.model]:g} Hz at most, not "
                f"{self.servo_hz:g}"
            )
        if self.control_hz > self.servo_rate:
            raise ValueError("control_hz must not exceed the servo rate")
        return self


class GripperSpec(_Strict):
    kind: Literal["robotiq_2f85", "robotiq_2f140", "digital", "none"] = "none"
    port: int = Field(default=63352, ge=1, le=65535)  # Robotiq URCap socket
    output: int = Field(default=0, ge=0, le=17)  # digital gripper: the tool/standard output


class CameraSpec(_Strict):
    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    kind: Literal["opencv", "realsense"] = "opencv"
    source: str  # OpenCV: a device index, a path or a URL; RealSense: the serial number
    width: int = Field(default=640, ge=16, le=4096)
    height: int = Field(default=480, ge=16, le=4096)
    fps: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=240.0)] = 30.0


class SafetySpec(_Strict):
    workspace: WorkspaceSpec = WorkspaceSpec()  # the twin's box: base frame, m
    tool_cone_deg: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=180.0)] = 45.0
    # m every corner of the tool (fingers open or closed, at any tilt) keeps above the table
    table_clearance: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=0.1)] = 0.003
    # m above the clearance within which the tool descends at table_approach_speed at most
    table_approach_height: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=0.5)] = 0.02
    table_approach_speed: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=2.0)] = 0.05
    max_step_translation: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=0.1)] = 0.02
    max_step_rotation: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=0.5)] = 0.1
    joint_margin: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=0.5)] = 0.05
    max_joint_speed: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=3.2)] = 1.0
    max_joint_acceleration: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=40.0)] = 4.0
    watchdog_ms: Annotated[float, Field(allow_inf_nan=False, ge=10.0, le=1000.0)] = 100.0


class CellFile(_Strict):
    """A whole real cell (see the module docstring)."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    twin: str  # a built-in cell or a scene spec file (relative to the cell file)
    arm: ArmSpec
    gripper: GripperSpec = GripperSpec()
    cameras: list[CameraSpec] = []
    safety: SafetySpec = SafetySpec()
    teleop: TeleopSpec = TeleopSpec()

    @model_validator(mode="after")
    def _unique_cameras(self) -> CellFile:
        names = [c.name for c in self.cameras]
        doubled = sorted({n for n in names if names.count(n) > 1})
        if doubled:
            raise ValueError(f"camera names must be unique; {', '.join(doubled)} repeat")
        return self


def parse_cell(data: object, source: str = "cell file") -> CellFile:
    """Validate a mapping as a :class:`CellFile`; every problem in one :class:`CellFileError`."""
    return validate_model(CellFile, data, source, CellFileError)


def load_cell(path: str | Path) -> CellFile:
    """Read and validate a cell file (YAML); its ``twin`` is resolved beside it."""
    path = Path(path)
    cell = parse_cell(read_yaml(path, "cell file", CellFileError), source=str(path))
    twin = path.parent / cell.twin
    if twin.suffix in (".yaml", ".yml"):
        if not twin.is_file():
            raise CellFileError(f"{path}: twin {cell.twin} does not exist beside the cell file")
        return cell.model_copy(update={"twin": str(twin)})
    return cell
