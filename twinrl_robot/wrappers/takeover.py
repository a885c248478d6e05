"""Operator takeover: a person (or the simulated operator) may take the controls."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from twinrl_robot.operator import Operator
from twinrl_robot.robot import Robot, Sent, require_privileged
from twinrl_robot.wrappers.base import RobotWrapper
from twinrl_sim.tasks import Task, TaskConfig


class OperatorTakeover(RobotWrapper):
    """Before every step the operator sees the latest observation and may act instead
    of the action source; the step then reports ``intervention``. On the first step of
    a takeover the arm is held where it is, so the operator starts from there.

    An operator that judges the task's progress (the simulated one) reads it from the
    privileged channel and so works only in a simulated cell; a teleop device does not.
    """

    def __init__(self, robot: Robot, operator: Operator, task: Task) -> None:
        super().__init__(robot)
        self.operator, self.task = operator, task
        self._channel = (
            require_privileged(robot, "the simulated operator")
            if getattr(operator, "judges_progress", False)
            else None
        )
        self._observation: dict[str, np.ndarray] | None = None
        self._intervening = False

    def reset(self, config: Any) -> dict[str, np.ndarray]:
        self._observation = self.robot.reset(config)
        self.operator.reset(self.task, TaskConfig.from_dict(config))
        self._intervening = False
        return self._observation

    def observe(self) -> dict[str, np.ndarray]:
        self._observation = self.robot.observe()
        return self._observation

    def act(self, action: np.ndarray) -> Sent:
        if self._observation is None:
            raise RuntimeError("reset the robot before acting")
        progress = self._channel.progress if self._channel is not None else None
        takeover = self.operator.intervene(self._observation, progress)
        if takeover is None:
            self._intervening = False
            return self.robot.act(action)
        if not self._intervening:
            self.robot.hold()
            self._intervening = True
        return replace(self.robot.act(takeover), intervention=True)
