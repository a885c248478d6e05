"""Replaying a logged episode: its joint targets and gripper commands, re-sent step by
step through the robot's safety layer (``servo_joints``), so that a real arm retraces
what it (or the twin, or another arm) did. The replay records the logged actions."""

from __future__ import annotations

import numpy as np

from twinrl_data.schema import ACTION, JOINT_TARGET, Episode
from twinrl_robot.errors import RobotError
from twinrl_robot.loop import JointCommand
from twinrl_sim.tasks import Task, TaskConfig


class ReplaySource:
    """The action source that re-sends ``episode``'s joint targets, one per step."""

    def __init__(self, episode: Episode) -> None:
        if JOINT_TARGET not in episode.data or ACTION not in episode.data:
            raise RobotError(
                f"episode {episode.meta.episode_id} has no '{JOINT_TARGET}' to replay; only "
                "episodes recorded by a robot loop carry the joint targets it sent"
            )
        self.targets = np.asarray(episode.data[JOINT_TARGET], float)
        self.actions = np.asarray(episode.data[ACTION], np.float32)
        self._step = 0

    def __len__(self) -> int:
        return len(self.targets)

    def reset(self, task: Task, config: TaskConfig) -> None:
        self._step = 0

    def act(self, observation: dict[str, np.ndarray]) -> JointCommand:
        t = min(self._step, len(self.targets) - 1)
        self._step += 1
        return JointCommand(self.targets[t], float(self.actions[t][6]), self.actions[t])

    def interrupted(self) -> None:
        """A person took the controls: the replay cannot resume where the arm now is."""
        raise RobotError("the replay was interrupted by a takeover; start it again")


def check_replay_start(robot: object, source: ReplaySource) -> None:
    """Refuse a replay whose first target lies outside a real arm's safety limits (the
    guard would otherwise clip its way there from wherever the arm stands)."""
    guard = getattr(getattr(robot, "unwrapped", robot), "guard", None)
    if guard is not None:
        guard.check_start(source.targets[0], "the replay's start pose")
