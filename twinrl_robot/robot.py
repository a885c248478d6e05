"""The robot protocol every caller is typed against, and the privileged channel.

A :class:`Robot` is a cell at its control rate: ``reset`` brings it to a task
configuration, ``act`` executes one control step of the episode contract's 7-D action,
``observe`` reads its sensors into a dict keyed like the contract
(``observation.state``, ``observation.effort``, ``observation.images.<camera>``).
Backends (the plant, the twin; a UR arm next) are opened in one place,
:func:`twinrl_robot.backends.open_robot`; behaviour that is not the arm's own (safety
limits, an operator's takeover, the grasp hold, sensor noise) stacks over a robot as
wrappers (:mod:`twinrl_robot.wrappers`).

What only a simulation can know (the task's progress, success, object poses) is *not*
part of the protocol: it is reached through ``robot.privileged``, which is ``None`` on
a real cell. Code that needs it calls :func:`require_privileged` and so refuses a real
robot with a clear error; code that does not never touches it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from twinrl_robot.errors import PrivilegedStateError
from twinrl_sim.tasks import Progress


@dataclass(frozen=True)
class Sent:
    """What one control step sent to the arm.

    ``action`` is the 7-D action executed (after every wrapper: clipped by the safety
    limits, held while the gripper closes, or an operator's); ``joint_target`` the
    servo targets (rad) the backend streamed for it; ``intervention`` whether a person
    (or the simulated operator) chose the action instead of the action source.
    """

    action: np.ndarray
    joint_target: np.ndarray
    intervention: bool = False


@runtime_checkable
class Privileged(Protocol):
    """What only a simulated cell knows: the task's ground truth after the last step."""

    @property
    def progress(self) -> Progress:
        """The task's progress terms and success (what a person watching judges)."""
        ...

    @property
    def success(self) -> bool: ...

    @property
    def environment_names(self) -> list[str]:
        """Names of :meth:`environment_state`'s entries (``<object>.x``, ...)."""
        ...

    def environment_state(self) -> np.ndarray:
        """Object poses (xyz + quaternion wxyz per object, base frame), float64."""
        ...


@runtime_checkable
class Robot(Protocol):
    """A robot cell at the control rate (see the module docstring).

    ``world`` is the episode contract's ``real``, ``twin`` or ``plant``; ``names`` maps
    each observation vector (``observation.state``, ...) to the names of
    its entries, as episodes record them. ``hold()`` stops the arm where it is and
    re-anchors the command there (when an operator takes the controls);
    ``servo_joints(q, gripper)`` holds joint targets (rad) for one control period, as
    UR's servoJ does (excitation, replay). ``privileged`` is ``None`` on a real cell.
    """

    control_hz: float
    world: str
    names: dict[str, list[str]]
    privileged: Privileged | None

    def reset(self, config: Any) -> dict[str, np.ndarray]: ...

    def observe(self) -> dict[str, np.ndarray]: ...

    def act(self, action: np.ndarray) -> Sent: ...

    def hold(self) -> None: ...

    def servo_joints(self, joint_target: np.ndarray, gripper: float) -> Sent: ...

    def close(self) -> None: ...


def require_privileged(robot: Robot, needed_for: str) -> Privileged:
    """The robot's privileged channel, or a :class:`PrivilegedStateError` saying that
    ``needed_for`` (e.g. "the simulated operator") works only in a simulated cell."""
    channel = robot.privileged
    if channel is None:
        raise PrivilegedStateError(
            f"{needed_for} needs the task's ground truth (progress, success or object poses), "
            "which only a simulated cell (the plant or the twin) knows; on a real robot use a "
            "person's judgement or a reward classifier instead"
        )
    return channel
