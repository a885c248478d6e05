"""The grasp hold: the arm keeps still while the gripper closes."""

from __future__ import annotations

from typing import Any

import numpy as np

from twinrl_data.schema import STATE
from twinrl_robot.robot import Robot, Sent
from twinrl_robot.wrappers.base import RobotWrapper
from twinrl_sim.tasks.expert import FINGERS_STILL, GRIPPER_CLOSED


class HoldRule:
    """Holds the arm while the gripper closes: from the step the gripper command turns
    to close, the arm's motion (the action's first six entries) is zeroed for ``settle``
    steps and then for as long as the fingers keep moving, so the arm lifts only once
    they have closed on the object.

    One per episode (:meth:`reset` at its start). Call it at every control step with
    the observation's ``observation.state`` (whose last entry is ``gripper.opening``)
    and the action about to be executed; ``applies=False`` (an operator's action) keeps
    track of the gripper without changing the action.
    """

    def __init__(self, settle: int = 2) -> None:
        self.settle = settle
        self.reset()

    def reset(self) -> None:
        self._closing_steps = 0
        self._opening: float | None = None

    def __call__(self, state: np.ndarray, action: np.ndarray, applies: bool = True) -> np.ndarray:
        opening = float(state[-1])
        moving = self._opening is not None and abs(opening - self._opening) >= FINGERS_STILL
        self._opening = opening
        if action[-1] < GRIPPER_CLOSED:
            self._closing_steps = 0
            return action
        self._closing_steps += 1
        if applies and (self._closing_steps <= self.settle or moving):
            action = np.array(action, copy=True)
            action[:6] = 0.0
        return action


class GraspHold(RobotWrapper):
    """A robot whose actions follow :class:`HoldRule`, reading the gripper opening from
    every observation that passes through it.

    Stack it over the operator's takeover (:class:`~twinrl_robot.wrappers.OperatorTakeover`):
    it then holds the action source's actions, and a person who takes the controls is
    never held.
    """

    def __init__(self, robot: Robot, settle: int = 2) -> None:
        super().__init__(robot)
        self.rule = HoldRule(settle)
        self._state: np.ndarray | None = None

    def reset(self, config: Any) -> dict[str, np.ndarray]:
        self.rule.reset()
        return self._seen(self.robot.reset(config))

    def observe(self) -> dict[str, np.ndarray]:
        return self._seen(self.robot.observe())

    def _seen(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        self._state = observation[STATE]
        return observation

    def act(self, action: np.ndarray) -> Sent:
        if self._state is None:
            raise RuntimeError("reset the robot before acting")
        return self.robot.act(self.rule(self._state, action))
