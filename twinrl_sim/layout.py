"""The names of a compiled cell's parts, which the effects, the controller and the
tasks address it by."""

from __future__ import annotations

from dataclasses import dataclass

MOUNT_BODY = "robot_mount"  # the body the arm's base stands on (its pose: the base frame)


@dataclass(frozen=True)
class CellLayout:
    """Names of the parts of a compiled cell."""

    arm_joints: tuple[str, ...]
    arm_actuators: tuple[str, ...]
    flange_body: str
    tcp_site: str
    gripper_actuator: str | None
    gripper_joint: str | None
    table_body: str
    table_geom: str
    manipulated: tuple[str, ...]
    placed: tuple[str, ...]
    cameras: tuple[str, ...]
    home_qpos: tuple[float, ...]
