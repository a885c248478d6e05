"""Sensor noise: what makes a simulated cell's readings look like a real arm's."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinrl_data.schema import EFFORT, ENVIRONMENT_STATE, STATE
from twinrl_robot.errors import RobotError
from twinrl_robot.robot import Robot
from twinrl_robot.wrappers.base import ObservationWrapper


@dataclass(frozen=True)
class NoiseLevels:
    """Standard deviations of the sensor noise."""

    joint_noise: float = 2e-4  # rad, on joint positions
    velocity_noise: float = 2e-3  # rad/s, on joint velocities
    tcp_noise: float = 3e-4  # m, on the reported TCP position
    object_noise: float = 1e-3  # m, on tracked object positions
    torque_noise: float = 0.05  # N m, on reported joint torques

    def __post_init__(self) -> None:
        for name in ("joint_noise", "velocity_noise", "tcp_noise", "object_noise", "torque_noise"):
            if getattr(self, name) < 0:
                raise RobotError(f"noise level {name} must be >= 0, got {getattr(self, name)}")


class SensorNoise(ObservationWrapper):
    """Adds Gaussian noise to joint positions and velocities, the TCP position, tracked
    object positions and joint torques, drawn in that order from one seeded stream."""

    def __init__(self, robot: Robot, levels: NoiseLevels, seed: int | None = None) -> None:
        super().__init__(robot)
        self.levels = levels
        self.rng = np.random.default_rng(seed)
        names = robot.names[STATE]
        self._joints = sum(name.startswith("q.") for name in names)
        self._tcp = names.index("tcp.x")

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        levels, n = self.levels, self._joints
        state = observation[STATE].astype(np.float64)
        noise = np.zeros_like(state)
        noise[:n] = self.rng.normal(0, levels.joint_noise, n)
        noise[n : 2 * n] = self.rng.normal(0, levels.velocity_noise, n)
        noise[self._tcp : self._tcp + 3] = self.rng.normal(0, levels.tcp_noise, 3)
        noisy = dict(observation)
        noisy[STATE] = (state + noise).astype(np.float32)
        if ENVIRONMENT_STATE in observation:
            env = observation[ENVIRONMENT_STATE].astype(np.float64)
            env_noise = np.zeros_like(env)
            for i in range(0, len(env), 7):
                env_noise[i : i + 3] = self.rng.normal(0, levels.object_noise, 3)
            noisy[ENVIRONMENT_STATE] = (env + env_noise).astype(np.float32)
        if EFFORT in observation:
            torques = observation[EFFORT].astype(np.float64)
            torques = torques + self.rng.normal(0, levels.torque_noise, len(torques))
            noisy[EFFORT] = torques.astype(np.float32)
        return noisy
