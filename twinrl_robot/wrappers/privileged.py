"""Object poses from a simulation's ground truth, as a tracker on a real cell would give."""

from __future__ import annotations

import numpy as np

from twinrl_data.schema import ENVIRONMENT_STATE
from twinrl_robot.robot import Robot, require_privileged
from twinrl_robot.wrappers.base import ObservationWrapper


class PrivilegedObservation(ObservationWrapper):
    """Adds ``observation.environment_state`` (object poses) from the privileged channel.

    Policies, experts and operators that read object poses need it; a real cell has no
    privileged channel, so wrapping one is refused (a tracker would take this place).
    """

    def __init__(self, robot: Robot, needed_for: str = "object poses in the observation"):
        super().__init__(robot)
        self._channel = require_privileged(robot, needed_for)

    @property
    def names(self) -> dict[str, list[str]]:
        return {**self.robot.names, ENVIRONMENT_STATE: self._channel.environment_names}

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {**observation, ENVIRONMENT_STATE: self._channel.environment_state()}
