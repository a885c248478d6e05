"""Batched simulation: many configurations of one task at once, on threads.

Two shapes of work:

- :class:`BatchRollout` replays open-loop joint-target sequences (logged commands,
  synthesized demos) for many configurations: every episode is one window of the
  twin's replay engine, all in one threaded ``mujoco.rollout`` call.
- :class:`BatchEnv` steps ``num_envs`` twin envs in closed loop: a policy sees each
  observation batch and acts; the IK runs per env in Python and the physics of all envs
  runs in one threaded call per control step.

:class:`BatchEnv` carries the whole integration state (warm start included) between
calls: its results are bit-identical to stepping each env alone. :class:`BatchRollout`
and :func:`~twinrl_sim.replay.replay` run the same engine and agree exactly.

For many envs over worker processes or a Ray cluster, :class:`~twinrl_sim.sharded.
ShardedBatchEnv` splits them into shards with the same API. For one env per worker
process, the Gymnasium vector API works on the registered ids
(``gymnasium.make_vec("twinrl_sim:twinrl/PickPlace-v0", num_envs=4,
vectorization_mode="async", vector_kwargs={"context": "spawn"})``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from mujoco import batch as mj_batch
from mujoco.rollout import Rollout

from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.control import action_bounds
from twinrl_sim.errors import TwinError
from twinrl_sim.tasks import Task, TaskConfig, make_task
from twinrl_sim.windowed import Starts, WindowedReplay

STATE = mujoco.mjtState.mjSTATE_INTEGRATION


def _threads(nthread: int | None) -> int:
    return nthread if nthread is not None else max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class BatchResult:
    """Physics states at every control step of every episode.

    ``states`` has shape (B, T + 1, nstate) (``mjSTATE_FULLPHYSICS``; row 0 is the
    initial state). :meth:`arm_q` and :meth:`qpos` slice it.
    """

    states: np.ndarray
    nq: int
    arm_qpos: np.ndarray

    def qpos(self) -> np.ndarray:
        """All generalised positions, shape (B, T + 1, nq). Row layout: time, then qpos."""
        return self.states[..., 1 : 1 + self.nq]

    def arm_q(self) -> np.ndarray:
        """Arm joint positions (rad), shape (B, T + 1, n_arm)."""
        return self.qpos()[..., self.arm_qpos]


class BatchRollout:
    """Open-loop rollouts of logged/planned joint targets for many configurations: one
    window of the twin's replay engine (:mod:`twinrl_sim.windowed`) per configuration.

    Args:
        task: task name or instance.
        effects: effects added to the task's scene.
        nthread: worker threads (default: all cores).
    """

    def __init__(
        self, task: str | Task, *, effects: dict | None = None, nthread: int | None = None
    ) -> None:
        self.task = make_task(task) if isinstance(task, str) else task
        self.cell = Cell(compile_scene(self.task.scene, extra_effects=effects))
        self.model = self.cell.model
        self.pool = Rollout(nthread=_threads(nthread))
        self.engine = WindowedReplay(self.cell.layout, 1.0 / self.cell.control_dt, self.pool)

    def initial_states(self, configs: list[TaskConfig | dict]) -> Starts:
        """The states and inputs of ``configs`` as the env's reset makes them (B rows)."""
        starts = []
        for config in configs:
            self.task.start(self.cell, TaskConfig.from_dict(config))
            starts.append(Starts.capture(self.model, self.cell.data))
        return Starts(
            np.concatenate([s.state for s in starts]), np.concatenate([s.inputs for s in starts])
        )

    def run(
        self,
        configs: list[TaskConfig | dict],
        joint_targets: np.ndarray,
        gripper: np.ndarray | None = None,
    ) -> BatchResult:
        """Replay ``joint_targets`` (B, T, n_arm) from each configuration."""
        targets = np.asarray(joint_targets, float)
        n_arm = len(self.cell.arm_act)
        if targets.ndim != 3 or targets.shape[2] != n_arm:
            raise TwinError(f"joint_targets must have shape (B, T, {n_arm}), got {targets.shape}")
        if len(configs) != len(targets):
            raise TwinError(f"{len(configs)} configs but {len(targets)} target sequences")
        batch, steps, _ = targets.shape
        grip = np.zeros((batch, steps)) if gripper is None else np.asarray(gripper, float)
        if grip.shape != (batch, steps):
            raise TwinError(f"gripper must have shape ({batch}, {steps}), got {grip.shape}")
        starts = self.initial_states(configs)
        ticks, _ = self.engine.rollout([self.model], starts, targets, grip)
        states = np.concatenate([starts.state[:, None], ticks[0]], axis=1)
        return BatchResult(states, self.model.nq, self.cell.arm_qpos)

    def close(self) -> None:
        self.pool.close()
        self.cell.close()


class BatchEnv:
    """``num_envs`` copies of a task's twin env stepped together in closed loop.

    ``reset(configs)`` returns an observation batch (dict of arrays with a leading env
    axis); ``step(actions)`` applies one action per env and returns ``(obs, reward,
    terminated, truncated, info)`` batches. Finished envs keep their last state until
    the next :meth:`reset` (no autoreset: the caller decides what to log and resample).
    ``cameras`` adds those cameras' images to every observation (rendered per env).
    """

    def __init__(
        self,
        task: str | Task,
        num_envs: int,
        *,
        effects: dict | None = None,
        reward: str = "sparse",
        nthread: int | None = None,
        cameras: tuple[str, ...] = (),
    ) -> None:
        if num_envs < 1:
            raise TwinError(f"num_envs must be at least 1, got {num_envs}")
        self.task = make_task(task) if isinstance(task, str) else task
        scene = compile_scene(self.task.scene, extra_effects=effects)
        self.cells = [Cell(scene) for _ in range(num_envs)]
        self.model = scene.model
        self.num_envs = num_envs
        self.reward_mode = reward
        self._sims = mj_batch.Batch(self.model, nsim=num_envs, nthread=_threads(nthread))
        self._trackers: list[Any] = [None] * num_envs
        self._steps = np.zeros(num_envs, dtype=int)
        self._low, self._high = action_bounds()
        self.cameras = tuple(cameras)

    def contract_names(self) -> dict[str, list[str]]:
        """The names of the observation's and the command's columns (the episode
        contract's ``names``)."""
        return self.cells[0].contract_names()

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {
            "observation.state": np.stack([c.state_vector() for c in self.cells]),
            "observation.environment_state": np.stack([c.environment_vector() for c in self.cells]),
        }
        for camera in self.cameras:
            obs[f"observation.images.{camera}"] = np.stack([c.render(camera) for c in self.cells])
        return obs

    def reset(self, configs: list[TaskConfig | dict]) -> dict[str, np.ndarray]:
        if len(configs) != self.num_envs:
            raise TwinError(f"reset needs {self.num_envs} configs, got {len(configs)}")
        for i, (cell, config) in enumerate(zip(self.cells, configs, strict=True)):
            self._trackers[i] = self.task.start(cell, TaskConfig.from_dict(config))
        self._steps[:] = 0
        return self._obs()

    def step(
        self, actions: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        actions = np.clip(np.asarray(actions, float), self._low, self._high)
        if actions.shape != (self.num_envs, len(self._low)):
            raise TwinError(
                f"actions must have shape ({self.num_envs}, {len(self._low)}), got {actions.shape}"
            )
        targets = np.empty((self.num_envs, len(self.cells[0].arm_act)))
        rows = self._sims.state
        for i, cell in enumerate(self.cells):
            targets[i] = cell.controller.joint_targets(actions[i], cell.data.qpos[cell.arm_qpos])
            cell.data.ctrl[cell.arm_act] = targets[i]
            if cell.gripper_act is not None:
                cell.data.ctrl[cell.gripper_act] = np.clip(actions[i, 6], 0.0, 1.0)
            mujoco.mj_getState(self.model, cell.data, rows[i], STATE)
        self._sims.step(nstep=self.cells[0].substeps)
        rewards = np.empty(self.num_envs)
        success = np.zeros(self.num_envs, dtype=bool)
        for i, cell in enumerate(self.cells):
            mujoco.mj_setState(self.model, cell.data, rows[i], STATE)
            mujoco.mj_forward(self.model, cell.data)
            progress = self._trackers[i].update()
            success[i] = progress.success
            rewards[i] = self.task.reward(progress, self.reward_mode)
        self._steps += 1
        truncated = (self._steps >= self.task.max_steps) & ~success
        info = {"command.joint_target": targets.astype(np.float32), "success": success}
        return self._obs(), rewards, success.copy(), truncated, info

    def close(self) -> None:
        for cell in self.cells:
            cell.close()
