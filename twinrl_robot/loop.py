"""The robot loop: observe, choose an action, send it through the wrappers to the
robot, record the step. Every producer of episodes runs it; only the action source
differs (a policy, the scripted expert, an excitation trajectory; teleop and replay
next).

The loop never waits for learning: whatever trains the policy runs elsewhere (see
:mod:`twinrl_learn.learner`) and hands the source new weights between episodes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from twinrl_data.recorder import Recorder
from twinrl_data.schema import EpisodeMeta, step_record
from twinrl_robot.errors import RobotError
from twinrl_robot.realtime import realtime_thread
from twinrl_robot.robot import Robot, Sent, require_privileged
from twinrl_robot.wrappers.base import layers
from twinrl_sim.tasks import Progress, Task, TaskConfig

Judge = Callable[[dict[str, np.ndarray]], bool]
"""Whether the task has succeeded, given the observation after the last step (the
privileged success in a simulated cell; a person's key or a reward classifier on a
real one)."""


@dataclass(frozen=True)
class JointCommand:
    """A step given as joint targets (rad) and a gripper command instead of an
    end-effector action (excitation, replay); ``action`` is the end-effector motion it
    amounts to, which the episode records."""

    joint_target: np.ndarray
    gripper: float
    action: np.ndarray


@runtime_checkable
class ActionSource(Protocol):
    """Chooses the action of every control step of an episode."""

    def reset(self, task: Task, config: TaskConfig) -> None: ...

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray | JointCommand: ...

    def interrupted(self) -> None:
        """An operator acted instead of this source: whatever it planned ahead is stale."""
        ...


@dataclass(frozen=True)
class EpisodeResult:
    """How an episode went."""

    success: bool
    steps: int
    interventions: int
    path: Path | None  # the recorded episode, when a recorder was given
    periods: tuple[float, ...] = ()  # s between consecutive control steps (wall clock)


def _backend(robot: Robot) -> Robot:
    """The backend at the bottom of ``robot``'s stack (``robot`` itself if unwrapped)."""
    *_, backend = layers(robot)
    return backend


def sensor_counts(robot: Robot) -> dict:
    """What the backend's sensors delivered this episode (a real cell's cameras), if it says."""
    counts = getattr(_backend(robot), "sensor_counts", None)
    return counts() if callable(counts) else {}


def sensor_streams(robot: Robot) -> Any:
    """The backend's sensors at their own rates (a real cell's cameras and controller
    state: ``cameras``, ``samples``, ``start(live)``, ``stop()``), or ``None``."""
    streams = getattr(_backend(robot), "sensor_streams", None)
    return streams() if callable(streams) else None


def loop_priority(robot: Robot) -> int | None:
    """The SCHED_FIFO priority the backend asks for the loop's thread (a real cell's
    ``arm.realtime_priority``), or ``None``."""
    return getattr(_backend(robot), "loop_priority", None)


def observation_time(robot: Robot) -> float:
    """When the newest observation was taken, on the host's monotonic clock: a real
    cell's controller package time on its samples' clock (``observed_at``), so each step
    lines up with the state streamed at the controller's rate; otherwise now."""
    at = getattr(_backend(robot), "observed_at", None)
    return time.monotonic() if at is None else float(at)


def privileged_success(robot: Robot) -> Judge:
    """The judge of a simulated cell: its ground-truth success."""
    channel = require_privileged(robot, "judging success from the task's ground truth")
    return lambda _observation: channel.success


def hold_action(action: np.ndarray) -> np.ndarray:
    """The end-effector action that keeps the arm still and the gripper as ``action`` left it."""
    held = np.zeros_like(np.asarray(action, dtype=np.float32))
    held[6] = action[6]
    return held


def run_episode(
    robot: Robot,
    source: ActionSource,
    task: Task,
    config: TaskConfig,
    *,
    judge: Judge | None,
    max_steps: int | None = None,
    recorder: Recorder | None = None,
    meta: EpisodeMeta | None = None,
    on_step: Callable[[int, Sent], None] | None = None,
    until: Callable[[], bool] | None = None,
    ready: Callable[[dict[str, np.ndarray]], None] | None = None,
    note: Callable[[], str | None] | None = None,
    settle: int = 0,
) -> EpisodeResult:
    """Run one episode of ``task`` from ``config``; record it when ``recorder`` is given.

    ``judge`` ends the episode on success (the sparse reward follows it); ``None`` judges
    nothing (excitation: reward 0, never done early). ``max_steps`` defaults to the
    task's. ``until`` ends the episode after a step without success when it says so (a
    person's failure or discard key). ``ready`` is called with the first observation
    after the reset, before anything is recorded (a person sets the cell up and starts);
    ``note`` gives the words kept with the episode when it is saved. ``settle`` steps
    follow a success with the arm held still, recorded as successes too: the last frames
    then show the success itself (a person's key comes a moment after it too), which a
    reward classifier learns from. A simulated cell
    steps as fast as it can and counts its own time (``on_step`` may pace it); a real
    backend keeps the control rate itself (its servo loop).
    """
    if (recorder is None) != (meta is None):
        raise RobotError("give both a recorder and the episode's metadata, or neither")
    limit = task.max_steps if max_steps is None else max_steps
    observation = robot.reset(config)
    if ready is not None:
        ready(observation)
        observation = robot.observe()
    observed = observation_time(robot)
    source.reset(task, config)
    streams = sensor_streams(robot) if recorder is not None else None
    if recorder is not None and meta is not None:
        if streams is None:
            recorder.start_episode(meta)
        else:  # a live episode: every camera frame and controller sample at their rates
            recorder.start_episode(meta, cameras=streams.cameras, samples=streams.samples)
            streams.start(recorder.live)
    success, interventions, steps, settled = False, 0, 0, 0
    executed = np.zeros(7, np.float32)  # the last step's action (held while settling)
    stamps: list[float] = []
    try:
        # A real cell's loop thread ahead of the recorder's and the cameras' (its arm's
        # realtime_priority): the kernel runs it as soon as its period's sleep ends.
        with realtime_thread(loop_priority(robot)):
            for t in range(limit + settle):
                stamps.append(time.perf_counter())
                chosen = hold_action(executed) if success else source.act(observation)
                if isinstance(chosen, JointCommand):
                    sent = robot.servo_joints(chosen.joint_target, chosen.gripper)
                    executed, proposed = chosen.action, chosen.action
                else:
                    sent = robot.act(chosen)
                    executed, proposed = sent.action, chosen
                if sent.intervention:
                    source.interrupted()
                    interventions += 1
                following = robot.observe()
                following_at = observation_time(robot)
                if success:
                    settled += 1
                else:
                    success = judge(following) if judge is not None else False
                    steps = t + 1
                stopped = not success and until is not None and until()
                done = stopped or (settled == settle if success else t == limit - 1)
                if recorder is not None:
                    recorder.add_frame(
                        step_record(
                            observation,
                            executed,
                            sent.joint_target,
                            task.reward(Progress(success=success), "sparse") if judge else 0.0,
                            done,
                            success,
                            action_policy=proposed,
                            intervention=sent.intervention,
                        ),
                        observed,
                    )
                if on_step is not None:
                    on_step(t, sent)
                observation, observed = following, following_at
                if done:
                    break
    except BaseException as err:
        if streams is not None:
            streams.stop()
        if recorder is not None and recorder.recording:  # keep what was recorded, and why
            reason = str(err) or type(err).__name__
            recorder.save_episode(
                success=False, aborted=reason, sensors=sensor_counts(robot), note=note and note()
            )
        raise
    path = None
    if streams is not None:
        streams.stop()
    if recorder is not None:
        path = recorder.save_episode(
            success=success, sensors=sensor_counts(robot), note=note and note()
        )
    return EpisodeResult(
        success=success,
        steps=steps,
        interventions=interventions,
        path=path,
        periods=tuple(np.diff(stamps).tolist()),
    )
