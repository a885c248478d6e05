"""A simulated cell as a robot backend: the plant's hidden world or the twin itself.

It steps a twinrl_sim :class:`~twinrl_sim.cell.Cell` with the task's tracker and keeps
its own clock: ``elapsed_steps`` control steps at ``control_hz`` (10 Hz: 600 steps =
one real minute). Its readings are exact; the plant's sensor noise is a wrapper
(:class:`~twinrl_robot.wrappers.SensorNoise`). Unlike a real cell it has a privileged
channel: the task's progress and success and the objects' poses.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from twinrl_data.schema import EFFORT, ENVIRONMENT_STATE, effort_names
from twinrl_robot.errors import RobotError
from twinrl_robot.robot import Sent
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.tasks import Progress, Task, TaskConfig


class SimulatedCell:
    """One task's cell in MuJoCo, driven like a robot.

    Args:
        task: the task (its scene is the cell).
        effects: physical effects compiled into the cell on top of the scene's own (the
            plant's hidden effects; none for the twin).
        cameras: cameras rendered into every observation.
        effort: report joint torques (``observation.effort``) as a UR controller does.
        world: the episode contract's world label (``plant`` or ``twin``).
    """

    def __init__(
        self,
        task: Task,
        *,
        effects: dict[str, dict[str, Any]] | None = None,
        cameras: tuple[str, ...] = (),
        effort: bool = False,
        world: str = "twin",
    ) -> None:
        self.task, self.world = task, world
        self.cell = Cell(compile_scene(task.scene, extra_effects=effects or None))
        unknown = [c for c in cameras if c not in self.cell.layout.cameras]
        if unknown:
            cameras_here = list(self.cell.layout.cameras)
            raise RobotError(f"unknown camera(s) {unknown}; this cell has {cameras_here}")
        self.cameras = tuple(cameras)
        self.effort = effort
        self.control_hz = task.scene.physics.control_hz
        self.names = self.cell.contract_names()
        if effort:
            self.names[EFFORT] = effort_names(self.cell.layout.arm_joints)
        self.names.pop(ENVIRONMENT_STATE, None)  # privileged: see PrivilegedObservation
        self.privileged = _GroundTruth(self)
        self.elapsed_steps = 0
        self._tracker = None
        self._progress = Progress(success=False)

    @property
    def elapsed_seconds(self) -> float:
        """Real time the cell has run, counted in control steps."""
        return self.elapsed_steps / self.control_hz

    def reset(self, config: TaskConfig | dict) -> dict[str, np.ndarray]:
        self._tracker = self.task.start(self.cell, TaskConfig.from_dict(config))
        self._progress = self._tracker.update()
        return self.observe()

    def observe(self) -> dict[str, np.ndarray]:
        observation = {"observation.state": self.cell.state_vector()}
        if self.effort:
            observation[EFFORT] = self.cell.joint_torques()
        for camera in self.cameras:
            observation[f"observation.images.{camera}"] = self.cell.render(camera)
        return observation

    def act(self, action: np.ndarray) -> Sent:
        self._check_reset()
        action = np.asarray(action, np.float32)
        return self._stepped(action, self.cell.step(action).joint_target)

    def servo_joints(self, joint_target: np.ndarray, gripper: float) -> Sent:
        """Hold joint targets (rad) and a gripper command for one control period; the
        end-effector command then restarts from where the arm is."""
        self._check_reset()
        target = np.asarray(joint_target, float)
        self.cell.send(target, float(np.clip(gripper, 0.0, 1.0)))
        self.cell.hold()
        return self._stepped(np.zeros(7, np.float32), target)

    def hold(self) -> None:
        """Stop the arm where it is: the command is re-anchored at the measured pose
        (what a teleop takeover does before the operator's first motion)."""
        self.cell.hold()

    def close(self) -> None:
        self.cell.close()

    def _check_reset(self) -> None:
        if self._tracker is None:
            raise RuntimeError(f"reset the {self.world} to a configuration before acting")

    def _stepped(self, action: np.ndarray, joint_target: np.ndarray) -> Sent:
        self.elapsed_steps += 1
        # Track every step: some tasks accumulate progress (wiped marks).
        assert self._tracker is not None
        self._progress = self._tracker.update()
        return Sent(action=action, joint_target=np.asarray(joint_target, np.float32))

    def __repr__(self) -> str:
        return f"SimulatedCell({self.task.name})"


class _GroundTruth:
    """The privileged channel of a :class:`SimulatedCell`."""

    def __init__(self, cell: SimulatedCell) -> None:
        self._cell = cell

    @property
    def progress(self) -> Progress:
        return self._cell._progress

    @property
    def success(self) -> bool:
        return self._cell._progress.success

    @property
    def environment_names(self) -> list[str]:
        return self._cell.cell.environment_names

    def environment_state(self) -> np.ndarray:
        return self._cell.cell.environment_vector()
