"""The plant: a stand-in for the real cell, built from the twin's scene spec plus
hidden effects (physical ones and its ``appearance``), and observation noise.

It is stepped through the same :class:`~twinrl_robot.interface.Robot` interface as a
real UR driver and keeps its own clock: ``elapsed_steps`` control steps at
``control_hz`` (10 Hz: 600 steps = one real minute). It is never used as the twin and
nothing reads its hidden effects except to generate data.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data.schema import effort_names
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.control import action_bounds
from twinrl_sim.effects import load_effects, validate_effects
from twinrl_sim.tasks import Progress, Task, TaskConfig, make_task

DEFAULT_EFFECTS_FILE = Path(__file__).resolve().parent / "plants" / "default.yaml"


@dataclass(frozen=True)
class PlantSettings:
    """Sensor noise (standard deviations); how the plant looks is its ``appearance`` effect."""

    joint_noise: float = 2e-4  # rad, on joint positions
    velocity_noise: float = 2e-3  # rad/s, on joint velocities
    tcp_noise: float = 3e-4  # m, on the reported TCP position
    object_noise: float = 1e-3  # m, on tracked object positions
    torque_noise: float = 0.05  # N m, on reported joint torques

    def __post_init__(self) -> None:
        for name in ("joint_noise", "velocity_noise", "tcp_noise", "object_noise", "torque_noise"):
            if getattr(self, name) < 0:
                raise ValueError(f"PlantSettings.{name} must be >= 0, got {getattr(self, name)}")


class Plant:
    """A simulated real cell for one task.

    Args:
        task: task name or instance (its scene is the nominal cell).
        effects: hidden effects (mapping) or a path to an effects YAML; ``None`` uses
            the built-in plant (``plants/default.yaml``); ``{}`` means none.
        settings: sensor noise.
        seed: seeds the sensor noise.
        images: cameras to render into observations (default: none).
    """

    def __init__(
        self,
        task: str | Task,
        *,
        effects: dict[str, dict[str, Any]] | str | Path | None = None,
        settings: PlantSettings = PlantSettings(),
        seed: int | None = None,
        images: tuple[str, ...] = (),
    ) -> None:
        self.task = make_task(task) if isinstance(task, str) else task
        if effects is None:
            hidden = load_effects(DEFAULT_EFFECTS_FILE)
        elif isinstance(effects, str | Path):
            hidden = load_effects(effects)
        else:
            hidden = validate_effects(effects)
        self._hidden_effects = hidden
        scene = self.task.scene
        self._cell = Cell(compile_scene(scene, extra_effects=hidden))
        self.settings = settings
        self.control_hz = scene.physics.control_hz
        self.images = tuple(images)
        self.rng = np.random.default_rng(seed)  # sensor noise; a run checkpoints its state
        self._tracker = None
        self._progress = Progress(success=False)
        self._action_low, self._action_high = action_bounds()
        self.elapsed_steps = 0
        self.last_joint_target: np.ndarray | None = None
        self.state_names = self._cell.state_names
        self.environment_names = self._cell.environment_names
        self.effort_names = effort_names(self._cell.layout.arm_joints)

    def contract_names(self) -> dict[str, list[str]]:
        """Names of the vector entries of this cell's episodes (see ``Cell.contract_names``)."""
        return self._cell.contract_names()

    @property
    def elapsed_seconds(self) -> float:
        """Real time the plant has run, counted in control steps."""
        return self.elapsed_steps / self.control_hz

    @property
    def success(self) -> bool:
        """Ground-truth task success (stands in for a success classifier)."""
        return self._progress.success

    @property
    def progress(self) -> Progress:
        """Ground-truth task progress after the last step (what an operator watching
        the cell judges; the simulated operator reads it)."""
        return self._progress

    def reset(self, config: TaskConfig | dict) -> dict[str, np.ndarray]:
        self._tracker = self.task.start(self._cell, TaskConfig.from_dict(config))
        self._progress = self._tracker.update()
        self.last_joint_target = None
        return self.observe()

    def observe(self) -> dict[str, np.ndarray]:
        s = self.settings
        n = len(self._cell.layout.arm_joints)
        state = self._cell.state_vector().astype(np.float64)
        noise = np.zeros_like(state)
        noise[:n] = self.rng.normal(0, s.joint_noise, n)
        noise[n : 2 * n] = self.rng.normal(0, s.velocity_noise, n)
        noise[2 * n : 2 * n + 3] = self.rng.normal(0, s.tcp_noise, 3)
        env = self._cell.environment_vector().astype(np.float64)
        env_noise = np.zeros_like(env)
        for i in range(0, len(env), 7):
            env_noise[i : i + 3] = self.rng.normal(0, s.object_noise, 3)
        obs = {
            "observation.state": (state + noise).astype(np.float32),
            "observation.environment_state": (env + env_noise).astype(np.float32),
        }
        for cam in self.images:
            obs[f"observation.images.{cam}"] = self._cell.render(cam)
        return obs

    def act(self, action: np.ndarray) -> None:
        self._check_reset()
        action = np.clip(np.asarray(action, float), self._action_low, self._action_high)
        self._stepped(self._cell.step(action).joint_target)

    def _check_reset(self) -> None:
        if self._tracker is None:
            raise RuntimeError("reset the plant to a configuration before acting")

    def _stepped(self, joint_target: np.ndarray) -> None:
        """Bookkeeping after one control step."""
        self.last_joint_target = joint_target
        self.elapsed_steps += 1
        # Track every step: some tasks accumulate progress (wiped marks).
        self._progress = self._tracker.update()

    def joint_torques(self) -> np.ndarray:
        """Measured joint torques (N m), with sensor noise."""
        torques = self._cell.joint_torques()
        return torques + self.rng.normal(0, self.settings.torque_noise, len(torques))

    def servo_joints(self, joint_target: np.ndarray, gripper: float) -> None:
        """Hold joint targets (rad) and a gripper command for one control period; the
        end-effector command then restarts from where the arm is."""
        self._check_reset()
        target = np.asarray(joint_target, float)
        self._cell.send(target, float(np.clip(gripper, 0.0, 1.0)))
        self._cell.hold()
        self._stepped(target)

    def hold(self) -> None:
        """Stop the arm where it is: the command is re-anchored at the measured pose
        (what a teleop takeover does before the operator's first motion)."""
        self._cell.hold()

    def close(self) -> None:
        self._cell.close()
