"""Replay: regenerate a logged initial state and re-send a logged command sequence.

This is how the twin answers "what would the simulation have done with exactly these
joint targets?": log-driven debugging, and one window of the twin's replay engine
(:mod:`twinrl_sim.windowed`) that the gap workflow runs from measured states.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from mujoco.rollout import Rollout

from twinrl_data.schema import (
    ACTION,
    ENVIRONMENT_STATE,
    JOINT_TARGET,
    STATE,
    SUCCESS,
    Episode,
)
from twinrl_sim.cell import Cell
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks.base import Task, TaskConfig
from twinrl_sim.windowed import Starts, WindowedReplay


@dataclass(frozen=True)
class ReplayResult:
    """Signals at each control step, the initial state included (T + 1 rows).

    Attributes:
        state: ``observation.state`` rows, shape (T + 1, 20).
        environment_state: object poses, shape (T + 1, 7 * objects).
        success: task success after each step, shape (T + 1,).
    """

    state: np.ndarray
    environment_state: np.ndarray
    success: np.ndarray

    def __post_init__(self) -> None:
        rows = {len(self.state), len(self.environment_state), len(self.success)}
        if len(rows) != 1:
            raise TwinError(f"replay signals disagree in length: {sorted(rows)}")


def replay(
    task: Task,
    cell: Cell,
    config: TaskConfig,
    joint_targets: np.ndarray,
    gripper: np.ndarray | None = None,
) -> ReplayResult:
    """Reset ``cell`` to ``config`` and send each joint-target row for one control period
    (held or tracked, as the cell's servos do: :mod:`twinrl_sim.servo`).

    Args:
        joint_targets: shape (T, n_arm_joints), radians, as logged in ``command.joint_target``.
        gripper: shape (T,), gripper commands in [0, 1]; default: keep the gripper open.
    """
    targets = np.asarray(joint_targets, float)
    n_arm = len(cell.layout.arm_joints)
    if targets.ndim != 2 or targets.shape[1] != n_arm:
        raise TwinError(f"joint_targets must have shape (T, {n_arm}), got {targets.shape}")
    grip = np.zeros(len(targets)) if gripper is None else np.asarray(gripper, float)
    if grip.shape != (len(targets),):
        raise TwinError(f"gripper must have shape ({len(targets)},), got {grip.shape}")
    tracker = task.start(cell, config)
    states = [cell.state_vector()]
    env_states = [cell.environment_vector()]
    success = [tracker.update().success]
    if len(targets):
        start = Starts.capture(cell.model, cell.data)
        with Rollout(nthread=1) as pool:
            engine = WindowedReplay(cell.layout, 1.0 / cell.control_dt, pool)
            ticks, held = engine.rollout([cell.model], start, targets[None], grip[None])
        for row, tick in enumerate(ticks[0, 0]):
            engine.restore(cell.model, cell.data, tick, held[0, 0, row])
            states.append(cell.state_vector())
            env_states.append(cell.environment_vector())
            success.append(tracker.update().success)
    return ReplayResult(np.array(states), np.array(env_states), np.array(success))


def replayed_episode(episode: Episode, scene: SceneSpec | None = None) -> Episode:
    """The twin's answer to a logged ``episode``: its configuration regenerated in the
    twin of ``scene`` (default: its task's built-in twin) and its logged joint targets
    and gripper commands re-sent, as an episode of the same length (source ``replay``,
    world ``twin``), to draw over the logged one."""
    from twinrl_sim.build import compile_scene
    from twinrl_sim.tasks import make_task

    missing = [f for f in (JOINT_TARGET, ACTION) if f not in episode.data]
    if missing:
        raise TwinError(
            f"episode {episode.meta.episode_id} has no '{missing[0]}' to replay; only episodes "
            "recorded by a robot loop carry the joint targets it sent"
        )
    if not episode.meta.config:
        raise TwinError(
            f"episode {episode.meta.episode_id} does not say its task configuration, so the "
            "twin cannot set it up"
        )
    task = make_task(episode.meta.task)
    cell = Cell(compile_scene(scene or task.scene))
    try:
        result = replay(
            task,
            cell,
            TaskConfig.from_dict(episode.meta.config),
            episode.data[JOINT_TARGET][:-1],
            np.asarray(episode.data[ACTION], float)[:-1, -1],
        )
    finally:
        cell.close()
    meta = replace(
        episode.meta,
        episode_id=f"{episode.meta.episode_id}-twin",
        source="replay",
        world="twin",
        names={
            **episode.meta.names,
            STATE: cell.state_names,
            ENVIRONMENT_STATE: cell.environment_names,
        },
    )
    data = {
        STATE: result.state.astype(np.float32),
        ENVIRONMENT_STATE: result.environment_state.astype(np.float32),
        ACTION: np.asarray(episode.data[ACTION], np.float32),
        SUCCESS: result.success,
    }
    return Episode(meta, data)
