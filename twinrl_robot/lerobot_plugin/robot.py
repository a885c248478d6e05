"""A twinrl UR cell as a LeRobot :class:`~lerobot.robots.robot.Robot`.

The cell is opened by :func:`twinrl_robot.backends.open_robot`, as twinrl's own commands
open it, so every action passes the cell file's safety layer: the per-step translation
and rotation limits, then the joint guard (joint limits and margins, joint speed and
acceleration, the workspace box, the tool cone) before the servo stream, whose every
target refreshes the controller's watchdog. Nothing here talks to the arm directly.

What it reads, per step, in one controller request (see :class:`~twinrl_robot.ur.driver.URArm`):

* ``q.<joint>`` (rad), ``qd.<joint>`` (rad/s): the joints as the controller measures them;
* ``tcp.x tcp.y tcp.z`` (m, base frame) and ``tcp.qw tcp.qx tcp.qy tcp.qz``: the TCP from
  the twin's kinematics of those joints (not the controller's own TCP reading);
* ``gripper.opening`` (m): a Robotiq's own position reading, a switched gripper's
  commanded state (it has no sensor), 0 without a gripper;
* ``<camera>``: each chosen camera's newest frame (RGB, the cell file's size).

Names follow twinrl's episode contract, so lerobot's ``observation.state`` is exactly
the contract's and twinrl's tools read a recorded dataset as they read their own. The
action is the contract's end-effector step: ``dx dy dz`` (m), ``rx ry rz`` (rad, axis-angle,
base frame) and ``gripper`` (0 open, 1 closed), executed over one control period.
"""

from __future__ import annotations

import logging
from functools import cached_property
from typing import Any

import numpy as np
from lerobot.robots.robot import Robot as LeRobotRobot
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected

from twinrl_data.lerobot_io import ACTION_NAMES
from twinrl_data.schema import IMAGES_PREFIX, STATE
from twinrl_robot.backends import open_robot
from twinrl_robot.cell_file import CameraSpec
from twinrl_robot.lerobot_plugin.config import TwinrlURConfig
from twinrl_robot.robot import Robot
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import state_names

logger = logging.getLogger(__name__)


class TwinrlUR(LeRobotRobot):
    """A UR arm of a twinrl cell file (a real controller, or ``twinrl robot emulate``).

    ``connect`` reaches the controller, applies the cell's TCP, payload and watchdog,
    brings the arm to the task's start pose and starts servoing; each ``send_action``
    then executes one control step and returns when its control period ends (so
    lerobot's loop runs at the cell's ``control_hz``: give it that as its fps). The arm
    holds its last target between calls and while lerobot saves an episode.
    """

    config_class = TwinrlURConfig
    name = "twinrl_ur"

    def __init__(self, config: TwinrlURConfig) -> None:
        super().__init__(config)
        self.config = config
        opened = config.open()
        self.cell, self.task = opened.cell, opened.task
        self.cameras: dict[str, CameraSpec] = {c.name: c for c in opened.cameras}
        self.state_names = state_names(compile_scene(self.task.scene).layout.arm_joints)
        self._robot: Robot | None = None

    @cached_property
    def observation_features(self) -> dict[str, type | tuple[int, int, int]]:
        cameras = {name: (c.height, c.width, 3) for name, c in self.cameras.items()}
        return {**dict.fromkeys(self.state_names, float), **cameras}

    @cached_property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(ACTION_NAMES, float)

    @property
    def is_connected(self) -> bool:
        return self._robot is not None

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        """Open the cell and bring the arm to the task's start pose (a UR needs no
        calibration: ``calibrate`` is ignored)."""
        robot = open_robot(
            "real",
            self.task,
            cell=self.cell,
            cameras=tuple(self.cameras),
            effort=False,
            object_poses=False,
            emulated=self.config.emulated,
        )
        try:
            robot.reset(self.task.sample_config(np.random.default_rng(), "ID"))
        except BaseException:
            robot.close()
            raise
        self._robot = robot
        logger.info("%s connected: %r", self, robot)

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate: the controller knows its joints, the cell file its TCP."""

    def configure(self) -> None:
        """Nothing to configure: ``connect`` applies the cell file's settings."""

    @check_if_not_connected
    def get_observation(self) -> dict[str, Any]:
        assert self._robot is not None
        observed = self._robot.observe()
        state = observed[STATE]
        observation: dict[str, Any] = {
            name: float(value) for name, value in zip(self.state_names, state, strict=True)
        }
        for name in self.cameras:
            observation[name] = observed[IMAGES_PREFIX + name]
        return observation

    @check_if_not_connected
    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        """Execute one control step; returns the action as sent (clipped by the limits)."""
        assert self._robot is not None
        missing = [name for name in ACTION_NAMES if name not in action]
        if missing:
            raise ValueError(f"the action lacks {', '.join(missing)}; it is {ACTION_NAMES}")
        vector = np.array([float(action[name]) for name in ACTION_NAMES], np.float32)
        sent = self._robot.act(vector)
        return dict(zip(ACTION_NAMES, map(float, sent.action), strict=True))

    @check_if_not_connected
    def disconnect(self) -> None:
        """Stop servoing and the control program; the arm stays where it is."""
        assert self._robot is not None
        robot, self._robot = self._robot, None
        robot.close()
        logger.info("%s disconnected", self)
