"""Safety limits between every action source and the arm."""

from __future__ import annotations

import numpy as np

from twinrl_robot.errors import RobotError
from twinrl_robot.robot import Robot
from twinrl_robot.wrappers.base import ActionWrapper
from twinrl_sim.control import action_bounds


class SafetyLimits(ActionWrapper):
    """Clips each action to the per-step limits: at most ``MAX_TRANSLATION`` m and
    ``MAX_ROTATION`` rad per axis per control step, the gripper command to [0, 1].

    Clipping, not refusal: an action source that asks for more gets the most the
    limits allow. (The controller also keeps the TCP target inside the workspace box.)
    """

    def __init__(self, robot: Robot) -> None:
        super().__init__(robot)
        self.low, self.high = action_bounds()

    def action(self, action: np.ndarray) -> np.ndarray:
        if action.shape != self.low.shape:
            raise RobotError(
                f"an action is {self.low.shape[0]} numbers (dxyz, drotation, gripper), "
                f"got shape {action.shape}"
            )
        return np.clip(action, self.low, self.high)
