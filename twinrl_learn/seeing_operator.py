"""A simulated person who decides from what the cameras show, not from the plant.

:class:`~twinrl_robot.operator.SimulatedOperator` judges the task's progress from the
plant's ground truth and drives the scripted expert from the true object poses: a
person who knows where everything is to the millimetre. :class:`SeeingOperator` is the
same person with only their eyes: every step a pose estimator
(:mod:`twinrl_learn.perception`, trained on twin renders) says where the objects are
from the cameras and the arm's own pose; the operator's copy of the twin is posed with
the arm's measured joints and those estimates, and the task's progress (its tracker:
which marks a wipe has taken, say) is judged there. The takeover rule, the expert's
plan and the hand-back all run on what was seen; on its way to the grasp, the expert's
aim follows the object as it is seen better (estimates made from afar are centimetres
off, and sharpen as the wrist camera nears it), as a person's does. It needs no
privileged channel, so it also stands in for a person at an emulated cell whose ground
truth is not read.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from twinrl_data.schema import ENVIRONMENT_STATE, STATE, image_field
from twinrl_learn.errors import LearnError
from twinrl_learn.perception.estimator import PoseEstimator, rotation_from_code
from twinrl_robot.operator import OperatorRule, SimulatedOperator
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.tasks import Progress, Task, TaskConfig
from twinrl_sim.tasks.base import Tracker
from twinrl_sim.tasks.expert import ObsView

# How far each step moves the operator's aim toward where it now sees the object: a
# person's aim follows what they see, not every flicker of it.
AIM_GAIN = 0.3


def world_poses(estimates: np.ndarray, state: np.ndarray, tcp_index: int) -> np.ndarray:
    """Each object's world pose (n, 7: xyz, quaternion wxyz) from one row of a pose
    estimator's ``estimates`` (positions relative to the TCP in decimetres, base axes,
    then each orientation's 6-number code in the tool frame) and the ``state`` row
    holding the TCP's pose at ``tcp_index``."""
    count = len(estimates) // 9
    tcp = np.asarray(state[tcp_index : tcp_index + 3], float)
    tool = np.empty(9)
    mujoco.mju_quat2Mat(tool, np.asarray(state[tcp_index + 3 : tcp_index + 7], float))
    poses = np.empty((count, 7))
    codes = torch.as_tensor(np.asarray(estimates[3 * count :], np.float64).reshape(count, 6))
    relative = rotation_from_code(codes).numpy()  # each object's rotation in the tool frame
    for k in range(count):
        poses[k, :3] = tcp + estimates[3 * k : 3 * k + 3] / 10.0
        mujoco.mju_mat2Quat(poses[k, 3:], (tool.reshape(3, 3) @ relative[k]).ravel())
    return poses


class SeeingOperator(SimulatedOperator):
    """The simulated operator judging from ``estimator``'s view (module docstring)."""

    judges_progress = False  # it judges for itself, from what it sees

    def __init__(
        self, estimator: PoseEstimator, rule: OperatorRule | None = None, seed: int | None = None
    ) -> None:
        super().__init__(rule or OperatorRule(), seed)
        self.estimator = estimator
        self.cameras = tuple(estimator.config.cameras)
        self._cell: Cell | None = None
        self._tracker: Tracker | None = None
        self._scene_of: Task | None = None
        self._tcp_index = estimator.config.state_names.index("tcp.x")
        self._row_of = {name: k for k, name in enumerate(estimator.config.objects)}
        self.last_seen: np.ndarray | None = None  # (n, 7): the object poses it saw last
        self._aim: np.ndarray | None = None  # where it aims the grasp: the object, steadied

    def reset(self, task: Task, config: TaskConfig) -> None:
        super().reset(task, config)
        missing = set(task.scene.object_names) - set(self.estimator.config.objects)
        if missing:
            raise LearnError(
                f"the pose estimator does not see {sorted(missing)[0]}, which {task.name} "
                "needs; train one on this task's twin (`twinrl train perception`)"
            )
        if self._cell is None or self._scene_of is not task:
            if self._cell is not None:
                self._cell.close()
            self._cell, self._scene_of = Cell(compile_scene(task.scene)), task
        self._tracker = task.start(self._cell, config)  # where the person set things up

    def seen(self, observation: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], Progress]:
        """``observation`` with the object poses the estimator sees in its cameras, and
        the task's progress judged on them."""
        if self._cell is None or self._tracker is None or self.task is None:
            raise RuntimeError("reset the operator at the start of each episode")
        missing = [c for c in self.cameras if image_field(c) not in observation]
        if missing:
            raise LearnError(
                f"the operator watches camera {missing[0]}, which the robot does not record"
            )
        state = np.asarray(observation[STATE], np.float32)
        images = {c: np.asarray(observation[image_field(c)])[None] for c in self.cameras}
        with torch.no_grad():
            estimates = self.estimator.estimate(images, state[None])[0].numpy()
        poses = world_poses(estimates, state, self._tcp_index)
        seen = poses[[self._row_of[name] for name in self.task.scene.object_names]]
        self.last_seen = seen
        self._cell.pose(
            state[: len(self._cell.arm_qpos)],
            float(state[-1]),  # the gripper's measured opening
            {
                name: (pose[:3], pose[3:])
                for name, pose in zip(self.task.scene.object_names, seen, strict=True)
            },
        )
        environment = seen.ravel()
        return {**observation, ENVIRONMENT_STATE: environment.astype(np.float32)}, (
            self._tracker.update()
        )

    def intervene(
        self, observation: dict[str, np.ndarray], progress: Progress | None
    ) -> np.ndarray | None:
        """As the simulated operator, on what it sees (``progress`` is not read)."""
        seen, judged = self.seen(observation)
        return super().intervene(seen, judged)

    def _expert_action(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The expert's action, its grasp re-aimed at where the object is now seen
        (smoothed over steps by :data:`AIM_GAIN`): estimates made far from the object are
        centimetres off, and they sharpen as the wrist camera nears it."""
        assert self.expert is not None
        seen = self._seen_object(observation)
        if self._aim is not None:
            steadied = self._aim + AIM_GAIN * (seen - self._aim)
            if self.expert.reaim(steadied - self._aim):
                self._aim = steadied
        action = super()._expert_action(observation)
        if self._aim is None and "grasp" in self.expert.memory:  # chosen from this view
            self._aim = seen
        return action

    def _take_over(self, observation: dict[str, np.ndarray], progress: Progress) -> None:
        super()._take_over(observation, progress)
        self._aim = None  # set from the view its grasp is chosen on (_expert_action)

    def _seen_object(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        assert self.task is not None
        return ObsView(self.task.scene, observation).position(self.task.object_name)

    def close(self) -> None:
        if self._cell is not None:
            self._cell.close()
            self._cell = None
