"""Safety limits between every action source and the arm."""

from __future__ import annotations

import numpy as np

from twinrl_robot.errors import RobotError
from twinrl_robot.robot import Robot
from twinrl_robot.wrappers.base import ActionWrapper
from twinrl_sim.control import action_bounds


class SafetyLimits(ActionWrapper):
    """Clips each action to the per-step limits: at most ``MAX_TRANSLATION`` m and
    ``MAX_ROTATION`` rad per axis per control step, the gripper command to [0, 1], and,
    when given (a real cell's file), the translation's length to ``max_translation`` m
    and the rotation's angle to ``max_rotation`` rad, keeping their directions.

    Clipping, not refusal: an action source that asks for more gets the most the
    limits allow. (The controller keeps the TCP target inside the workspace box; a real
    cell's joint guard keeps every joint target inside the box, the tool cone and the
    joint limits, see :mod:`twinrl_robot.guard`.)
    """

    def __init__(
        self,
        robot: Robot,
        max_translation: float | None = None,
        max_rotation: float | None = None,
    ) -> None:
        super().__init__(robot)
        self.low, self.high = action_bounds()
        self.max_translation, self.max_rotation = max_translation, max_rotation

    def action(self, action: np.ndarray) -> np.ndarray:
        if action.shape != self.low.shape:
            raise RobotError(
                f"an action is {self.low.shape[0]} numbers (dxyz, drotation, gripper), "
                f"got shape {action.shape}"
            )
        clipped = np.clip(action, self.low, self.high)
        for part, limit in ((slice(0, 3), self.max_translation), (slice(3, 6), self.max_rotation)):
            norm = float(np.linalg.norm(clipped[part]))
            if limit is not None and norm > limit:
                clipped[part] *= limit / norm
        return clipped
