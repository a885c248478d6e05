"""Replaying a logged episode: its joint targets and gripper commands, re-sent step by
step through the robot's safety layer (``servo_joints``), so that a real arm retraces
what it (or the twin, or another arm) did. The replay records the logged actions."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import Recorder
from twinrl_data.schema import ACTION, JOINT_TARGET, STATE, Episode
from twinrl_robot.errors import RobotError
from twinrl_robot.loop import JointCommand, run_episode
from twinrl_robot.robot import Robot
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


@dataclass(frozen=True)
class Replayed:
    """A recorded replay: its file, its steps, and how far (RMS, rad) its measured joints
    ran from the logged ones, step by step."""

    path: Path
    steps: int
    joint_rms: float


def replay_episode(
    robot: Robot,
    episode: Episode,
    task: Task,
    recorder: Recorder,
    confirm: Callable[[str], bool] | None = None,
) -> Replayed:
    """Re-send ``episode``'s joint targets through ``robot``'s safety layer and record the
    replay as a new episode (source ``replay``); its configuration is the logged one.

    A start outside a real arm's limits is refused first; ``confirm`` (given the start
    pose, in words) may still say no, and then nothing moves."""
    source = ReplaySource(episode)
    check_replay_start(robot, source)
    start = ", ".join(f"{v:.3f}" for v in source.targets[0])
    if confirm is not None and not confirm(f"joints [{start}] rad"):
        raise RobotError("the replay was not confirmed; nothing was sent to the arm")
    config = TaskConfig.from_dict(episode.meta.config)
    meta = task.episode_meta(
        source="replay",
        world=robot.world,
        names=robot.names,
        config=config,
        region=episode.meta.region,
        policy=f"replay:{episode.meta.episode_id}",
    )
    result = run_episode(
        robot, source, task, config, judge=None, max_steps=len(source), recorder=recorder, meta=meta
    )
    assert result.path is not None
    logged = np.asarray(episode.data[STATE])[: result.steps, :6]
    measured = np.asarray(_recorded_states(result.path))[: len(logged), :6]
    rows = min(len(logged), len(measured))
    rms = float(np.sqrt(np.mean((logged[:rows] - measured[:rows]) ** 2))) if rows else 0.0
    return Replayed(result.path, result.steps, rms)


def _recorded_states(path: Path) -> np.ndarray:
    """The ``observation.state`` rows of a recorded episode file."""
    return read_episode(path, images=False).data[STATE]
