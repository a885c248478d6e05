"""The robot interface: what the plant implements now and a UR driver will later.

A robot is stepped at its control rate with the episode contract's 7-D action and
observed as a dict keyed like the contract (``observation.state``, optional
``observation.environment_state`` and ``observation.images.<camera>``).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Robot(Protocol):
    """A robot cell at the control rate.

    ``reset(config)`` brings the cell to a task configuration (programmatic in the
    plant, operator-guided on a real robot) and returns the first observation;
    ``act(action)`` executes one control step; ``observe()`` reads the sensors;
    ``hold()`` stops the arm where it is and re-anchors the command there (called when
    an operator takes the controls); ``servo_joints(q, gripper)`` holds joint targets
    (rad) for one control period, as UR's servoJ does (excitation, replay).
    """

    control_hz: float

    def reset(self, config: Any) -> dict[str, np.ndarray]: ...

    def observe(self) -> dict[str, np.ndarray]: ...

    def act(self, action: np.ndarray) -> None: ...

    def hold(self) -> None: ...

    def servo_joints(self, joint_target: np.ndarray, gripper: float) -> None: ...

    def close(self) -> None: ...
