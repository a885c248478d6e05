"""Gymnasium environments of the twin, one per task, following the episode contract.

Observations are a ``Dict`` keyed like the episode contract:

- ``observation.state``: float32[20] proprio (see :mod:`twinrl_sim.cell`);
- ``observation.environment_state``: float32[7 * objects] object poses (privileged);
- ``observation.images.<camera>``: uint8 HxWx3 when ``images=True``.

Actions are the contract's 7-D end-effector delta (m, rad, gripper in [0, 1]).
``reset(options={"config": cfg})`` regenerates a logged initial configuration exactly;
``options={"region": "OOD"}`` samples one in a region. Episodes terminate on success
and truncate after the task's ``max_steps`` control steps.

    >>> env = make("pick_place")
    >>> obs, info = env.reset(seed=0, options={"region": "ID"})
    >>> sorted(obs)
    ['observation.environment_state', 'observation.state']
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.control import action_bounds
from twinrl_sim.errors import TwinError
from twinrl_sim.replay import ReplayResult, replay
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import Task, TaskConfig, make_task

OBS_STATE = "observation.state"
OBS_ENV = "observation.environment_state"
OBS_IMAGES = "observation.images"


class TwinEnv(gym.Env[dict[str, np.ndarray], np.ndarray]):
    """One task in the twin.

    Args:
        task: a task name (``pick_place``, ...) or a :class:`Task` instance.
        scene: a scene spec replacing the task's built-in one (e.g. a reconstructed cell).
        effects: physical effects added to the scene (``name: {param: value}``).
        images: also return ``front``/``wrist`` (or ``cameras``) images.
        reward: ``sparse`` (+10 success, -0.05 per step) or ``dense``.
        region: default region for configurations sampled at reset (None: either).
        max_steps: episode length limit (default: the task's).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        task: str | Task = "pick_place",
        *,
        scene: SceneSpec | None = None,
        effects: dict[str, dict[str, Any]] | None = None,
        images: bool = False,
        cameras: tuple[str, ...] | None = None,
        reward: str = "sparse",
        region: str | None = None,
        max_steps: int | None = None,
        render_mode: str | None = None,
    ) -> None:
        self.task = make_task(task, scene) if isinstance(task, str) else task
        if reward not in ("sparse", "dense"):
            raise TwinError(f"reward must be 'sparse' or 'dense', got '{reward}'")
        if region is not None:
            self.task.region(region)
        self.reward_mode = reward
        self.region = region
        self.max_steps = max_steps or self.task.max_steps
        self.render_mode = render_mode
        self.cell = Cell(compile_scene(self.task.scene, extra_effects=effects))
        available = self.cell.layout.cameras
        self.cameras = tuple(cameras) if cameras is not None else (available if images else ())
        unknown = [c for c in self.cameras if c not in available]
        if unknown:
            raise TwinError(f"unknown camera(s) {unknown}; this cell has {list(available)}")
        low, high = action_bounds()
        self.action_space = gym.spaces.Box(low, high, dtype=np.float32)
        spaces: dict[str, gym.Space] = {
            OBS_STATE: gym.spaces.Box(-np.inf, np.inf, (len(self.cell.state_names),), np.float32),
            OBS_ENV: gym.spaces.Box(
                -np.inf, np.inf, (len(self.cell.environment_names),), np.float32
            ),
        }
        for cam in self.cameras:
            w, h = self.cell.model.cam_resolution[self.cell.model.camera(cam).id]
            spaces[f"{OBS_IMAGES}.{cam}"] = gym.spaces.Box(0, 255, (int(h), int(w), 3), np.uint8)
        self.observation_space = gym.spaces.Dict(spaces)
        self.config: TaskConfig | None = None
        self._tracker = None
        self._steps = 0

    @property
    def instruction(self) -> str:
        return self.task.instruction

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {OBS_STATE: self.cell.state_vector(), OBS_ENV: self.cell.environment_vector()}
        for cam in self.cameras:
            obs[f"{OBS_IMAGES}.{cam}"] = self.cell.render(cam)
        return obs

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"config", "region"}
        if unknown:
            raise TwinError(f"unknown reset option(s) {sorted(unknown)}; use 'config' or 'region'")
        if options.get("config") is not None:
            config = TaskConfig.from_dict(options["config"])
        else:
            config = self.task.sample_config(self.np_random, options.get("region", self.region))
        self.config = config
        self._tracker = self.task.start(self.cell, config)
        self._steps = 0
        progress = self._tracker.update()
        return self._obs(), self._info(progress, None)

    def step(
        self, action: np.ndarray
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self._tracker is None:
            raise RuntimeError("call reset() before step()")
        action = np.clip(
            np.asarray(action, np.float32), self.action_space.low, self.action_space.high
        )
        signals = self.cell.step(action)
        self._steps += 1
        progress = self._tracker.update()
        reward = self.task.reward(progress, self.reward_mode)
        terminated = progress.success
        truncated = self._steps >= self.max_steps and not terminated
        return (
            self._obs(),
            reward,
            terminated,
            truncated,
            self._info(progress, signals.joint_target),
        )

    def _info(self, progress, joint_target: np.ndarray | None) -> dict[str, Any]:
        assert self.config is not None
        info: dict[str, Any] = {
            "config": self.config.to_dict(),
            "region": self.task.region_of(self.config),
            "success": progress.success,
            "reward_terms": dict(progress.terms),
        }
        if joint_target is not None:
            info["command.joint_target"] = joint_target.astype(np.float32)
        return info

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return self.cell.render(self.cell.layout.cameras[0])

    def replay(
        self,
        config: TaskConfig | dict,
        joint_targets: np.ndarray,
        gripper: np.ndarray | None = None,
    ) -> ReplayResult:
        """Regenerate ``config`` and re-send logged joint targets; see :func:`replay`."""
        return replay(self.task, self.cell, TaskConfig.from_dict(config), joint_targets, gripper)

    def close(self) -> None:
        self.cell.close()


def make(task: str, **kwargs: Any) -> TwinEnv:
    """Create the twin env of ``task``; keyword arguments go to :class:`TwinEnv`."""
    return TwinEnv(task, **kwargs)
