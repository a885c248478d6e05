"""Wrappers stack behaviour over a :class:`~twinrl_robot.robot.Robot`, one behaviour
each, in the shape of Gymnasium's ``Wrapper`` / ``ActionWrapper`` /
``ObservationWrapper``: a wrapper is itself a robot and forwards what it does not
change, so any stack of them is typed and used as a robot.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from typing import Any

import numpy as np

from twinrl_robot.errors import RobotError
from twinrl_robot.robot import Privileged, Robot, Sent


class RobotWrapper:
    """A robot around ``robot`` that changes nothing until a subclass overrides it."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot

    @property
    def control_hz(self) -> float:
        return self.robot.control_hz

    @property
    def world(self) -> str:
        return self.robot.world

    @property
    def names(self) -> dict[str, list[str]]:
        return self.robot.names

    @property
    def privileged(self) -> Privileged | None:
        return self.robot.privileged

    @property
    def unwrapped(self) -> Robot:
        """The backend at the bottom of the stack."""
        inner = self.robot
        return inner.unwrapped if isinstance(inner, RobotWrapper) else inner

    def reset(self, config: Any) -> dict[str, np.ndarray]:
        return self.robot.reset(config)

    def observe(self) -> dict[str, np.ndarray]:
        return self.robot.observe()

    def act(self, action: np.ndarray) -> Sent:
        return self.robot.act(action)

    def hold(self) -> None:
        self.robot.hold()

    def servo_joints(self, joint_target: np.ndarray, gripper: float) -> Sent:
        return self.robot.servo_joints(joint_target, gripper)

    def close(self) -> None:
        self.robot.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.robot!r})"


class ActionWrapper(RobotWrapper, ABC):
    """Changes every action on its way down (a subclass defines :meth:`action`)."""

    def act(self, action: np.ndarray) -> Sent:
        return self.robot.act(self.action(np.asarray(action, np.float32)))

    @abstractmethod
    def action(self, action: np.ndarray) -> np.ndarray:
        """The action to send instead of ``action``."""


class ObservationWrapper(RobotWrapper, ABC):
    """Changes every observation on its way up (a subclass defines :meth:`observation`)."""

    def reset(self, config: Any) -> dict[str, np.ndarray]:
        return self.observation(self.robot.reset(config))

    def observe(self) -> dict[str, np.ndarray]:
        return self.observation(self.robot.observe())

    @abstractmethod
    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The observation to pass up instead of ``observation``."""


def layers(robot: Robot) -> Iterator[Robot]:
    """Every layer of a stack, outermost first, the backend last."""
    while True:
        yield robot
        if not isinstance(robot, RobotWrapper):
            return
        robot = robot.robot


def random_states(robot: Robot) -> dict[str, Any]:
    """The state of every random stream in the stack (layers with an ``rng``), keyed by
    position and class, so a run can checkpoint it and :func:`restore_random_states`."""
    return {
        f"{i}:{type(layer).__name__}": layer.rng.bit_generator.state
        for i, layer in enumerate(layers(robot))
        if isinstance(getattr(layer, "rng", None), np.random.Generator)
    }


def restore_random_states(robot: Robot, states: dict[str, Any]) -> None:
    """Put back what :func:`random_states` saved; a stack of another shape is an error."""
    current = random_states(robot)
    if set(current) != set(states):
        raise RobotError(
            f"the saved random streams {sorted(states)} do not match this robot's "
            f"{sorted(current)}; resume with the settings the run started with"
        )
    for i, layer in enumerate(layers(robot)):
        key = f"{i}:{type(layer).__name__}"
        if key in states:
            layer.rng.bit_generator.state = states[key]
