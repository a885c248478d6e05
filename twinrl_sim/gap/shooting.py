"""Forward replay with multiple shooting: each window of a measured episode restarts the
twin from the measured joint state and re-sends the logged joint targets.

A single replay of a long episode lets a small early error (a slightly different
friction) accumulate until everything disagrees; restarting every ``window`` steps from
what was measured keeps each comparison local, so that the residuals say which effect
acts where. When the episode logs joint torques, the replay also carries the inverse
dynamics comparison (``tau_id.*``, see :mod:`twinrl_sim.gap.inverse`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinrl_data import schema as contract
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.errors import TwinError
from twinrl_sim.gap.inverse import inverse_dynamics, inverse_model
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import TASKS, TaskConfig, make_task


@dataclass(frozen=True)
class ShootingReplay:
    """Measured and replayed signals of one episode, row-aligned (T rows).

    Row ``t`` of ``predicted`` is what the twin gave after ``t - start`` steps of the
    window that contains ``t``; at each window's first row it equals the measurement.
    """

    names: list[str]  # observation.state entry names (q.*, qd.*, tcp.*), then tau_id.*
    measured: np.ndarray  # (T, n)
    predicted: np.ndarray  # (T, n)
    window: np.ndarray  # (T,) index of the shooting window of each row
    step_in_window: np.ndarray  # (T,) 0 at each window start
    targets: np.ndarray  # (T, n_arm) joint targets sent at each row
    gripper: np.ndarray  # (T,) gripper command at each row
    fps: float

    def columns(self, prefix: str) -> list[int]:
        return [i for i, n in enumerate(self.names) if n.startswith(prefix)]


def _cell_for(scene: SceneSpec, effects: dict | None, fps: float) -> Cell:
    cell = Cell(compile_scene(scene, extra_effects=effects or None))
    steps = 1.0 / (fps * scene.physics.timestep)
    if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
        raise TwinError(
            f"the episode's {fps:g} Hz is not a whole number of the twin's "
            f"{scene.physics.timestep} s physics steps; import it with --fps "
            f"{scene.physics.control_hz:g} (or another divisor of {1 / scene.physics.timestep:g})"
        )
    cell.substeps = round(steps)
    return cell


def replay_windows(
    episode: contract.Episode,
    scene: SceneSpec,
    *,
    effects: dict | None = None,
    window: int = 20,
) -> ShootingReplay:
    """Replay ``episode`` in the twin built from ``scene`` (plus ``effects``), restarting
    from the measured joints every ``window`` steps."""
    if window < 2:
        raise TwinError(f"--window must be at least 2 steps, got {window}")
    names = list(episode.meta.names.get(contract.STATE, []))
    if contract.JOINT_TARGET not in episode.data:
        raise TwinError(
            f"episode {episode.meta.episode_id} has no command.joint_target; replay needs "
            "the joint targets that were sent"
        )
    cell = _cell_for(scene, effects, episode.meta.fps)
    try:
        arm = cell.layout.arm_joints
        index = {n: i for i, n in enumerate(names)}
        missing = [f"q.{j}" for j in arm if f"q.{j}" not in index]
        if missing:
            raise TwinError(f"episode {episode.meta.episode_id} lacks {missing[0]} in its state")
        q_cols = [index[f"q.{j}"] for j in arm]
        qd_cols = [index.get(f"qd.{j}") for j in arm]
        measured = episode.data[contract.STATE].astype(float)
        targets = episode.data[contract.JOINT_TARGET].astype(float)
        actions = episode.data.get(contract.ACTION)
        gripper = np.zeros(len(measured)) if actions is None else np.clip(actions[:, 6], 0, 1)
        task = make_task(episode.meta.task, scene) if episode.meta.task in TASKS else None
        config = (
            TaskConfig.from_dict(episode.meta.config)
            if task is not None and {"object", "target"} <= set(episode.meta.config)
            else None
        )
        # Entries the twin also produces are predicted; others (if any) stay measured.
        shared = [i for i, n in enumerate(names) if n in cell.state_names]
        twin_cols = [cell.state_names.index(names[i]) for i in shared]
        predicted = measured.copy()
        windows = np.arange(len(measured)) // window
        steps = np.arange(len(measured)) % window
        for start in range(0, len(measured) - 1, window):
            if config is not None:
                task.start(cell, config)
            else:
                cell.reset_robot()
            cell.data.qpos[cell.arm_qpos] = measured[start, q_cols]
            if all(c is not None for c in qd_cols):
                cell.data.qvel[cell.arm_dof] = measured[start, qd_cols]
            held = targets[start - 1] if start > 0 else measured[start, q_cols]
            cell.data.ctrl[cell.arm_act] = held
            cell.finish_reset()
            for t in range(start, min(start + window, len(measured)) - 1):
                cell.send(targets[t], float(gripper[t]))
                predicted[t + 1, shared] = cell.state_vector()[twin_cols]
        torques = inverse_dynamics(episode, inverse_model(scene, effects))
        if torques is not None:
            names = names + torques.names
            measured = np.concatenate([measured, torques.measured], axis=1)
            predicted = np.concatenate([predicted, torques.predicted], axis=1)
        return ShootingReplay(
            names, measured, predicted, windows, steps, targets, gripper, episode.meta.fps
        )
    finally:
        cell.close()
