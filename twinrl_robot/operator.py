"""Human-in-the-loop operators: who takes the controls from the policy, and when.

Real RL on a robot needs a person who corrects the policy when it goes wrong
(HiL-SERL, ConRFT, TwinRL all rely on it). :class:`Operator` is the hook the RL loop
calls at every control step: it returns an action while it holds the controls and
``None`` while the policy acts. A teleop device (a SpaceMouse driver) implements the
same two methods; :class:`SimulatedOperator` stands in for the person in the plant.

The simulated operator's rule (:class:`OperatorRule`), judged on the task's progress
terms (reach, grasp, place/wipe: each in [0, 1]; their sum is the *progress*):

- it **takes over** when the progress has not improved by ``min_progress`` for
  ``patience`` steps (the policy is stuck), has fallen ``regression`` below its best
  (the object was dropped or knocked away), or the fingers start closing while the TCP
  is more than ``funnel`` m across the object from where the expert would grasp (a
  grasp that is going to miss: the operator steps in before the stall it leads to),
  after a reaction delay of ``delay`` steps during which the policy keeps acting;
- it then drives the arm with the task's scripted expert, restarted from the measured
  state: from the lift if the object is already in the gripper; straight to the grasp
  (gripper open) if the arm is low beside the object, within ``correct_within`` m of
  the expert's grasp, as a person nudges a grasp that is slightly off; otherwise from
  the approach pose above the object; with hand jitter of ``noise`` m per step;
- it **hands back** once it has held the controls for ``min_control`` steps and the
  progress has risen ``handback_gain`` above the best the policy reached (the stall is
  resolved), or when its plan is done.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from twinrl_data.errors import SettingError
from twinrl_robot.errors import RobotError
from twinrl_sim.tasks import Progress, Task, TaskConfig
from twinrl_sim.tasks.expert import ObsView, ScriptedExpert


@runtime_checkable
class Operator(Protocol):
    """Someone who can take the controls from the policy during an episode.

    An operator that reads the task's progress sets ``judges_progress = True``: it is
    then given the progress from the robot's privileged channel (and refused on a real
    cell, which has none); otherwise ``progress`` is ``None``.
    """

    def reset(self, task: Task, config: TaskConfig) -> None: ...

    def intervene(
        self, observation: dict[str, np.ndarray], progress: Progress | None
    ) -> np.ndarray | None:
        """The operator's action for this step, or ``None`` to let the policy act."""
        ...


@dataclass(frozen=True)
class OperatorRule:
    """When the simulated operator takes over and hands back (see the module doc)."""

    patience: int = 10
    """Steps without progress before taking over."""
    min_progress: float = 0.02
    """What counts as progress."""
    regression: float = 0.5
    """A drop from the best progress that triggers a takeover."""
    delay: int = 3
    """Reaction time (steps) between noticing and acting."""
    handback_gain: float = 1.0
    """Progress above the policy's best before handing back (a grasp)."""
    min_control: int = 5
    """Steps held at least, once taken over."""
    noise: float = 0.002
    """Hand jitter, m per step (rotation: 5x in rad)."""
    funnel: float = 0.015
    """Operator: metres across the object a closing gripper may be from the expert's grasp
    before it takes over (0: only when the policy stalls)."""
    correct_within: float = 0.06
    """Operator: metres from the expert's grasp within which a low arm is corrected
    straight to it instead of backed off to the approach (0: never); correcting measured
    better (docs/results/defaults.md)."""

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if value < 0:
                raise SettingError(name, f"must be >= 0, got {value}")


class SimulatedOperator:
    """The scripted expert as an operator, following :class:`OperatorRule`."""

    judges_progress = True

    def __init__(self, rule: OperatorRule = OperatorRule(), seed: int | None = None) -> None:
        self.rule = rule
        self.rng = np.random.default_rng(seed)
        self.task: Task | None = None
        self.config: TaskConfig | None = None
        self.expert: ScriptedExpert | None = None
        self.takeovers = 0

    @property
    def in_control(self) -> bool:
        return self.expert is not None

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.task, self.config, self.expert = task, config, None
        self.takeovers = 0
        self._best = -np.inf
        self._stalled = 0
        self._countdown: int | None = None
        self._held = 0
        self._best_before = 0.0
        self._opening = float("nan")

    def intervene(
        self, observation: dict[str, np.ndarray], progress: Progress | None
    ) -> np.ndarray | None:
        if self.task is None:
            raise RuntimeError("reset the operator at the start of each episode")
        if progress is None:
            raise RobotError("the simulated operator judges the task's progress; pass it")
        value = float(sum(progress.terms.values()))
        closing = self._fingers_closing(observation)
        if self.expert is not None:
            self._held += 1
            resolved = value >= self._best_before + self.rule.handback_gain
            if self.expert.done or (self._held > self.rule.min_control and resolved):
                self.expert = None
                self._best, self._stalled = value, 0
                return None
            return self._expert_action(observation)
        if self._countdown is not None:
            self._countdown -= 1
            if self._countdown <= 0:
                self._take_over(observation, progress)
                return self._expert_action(observation)
            return None
        if value > self._best + self.rule.min_progress:
            self._best, self._stalled = value, 0
        else:
            self._stalled += 1
        stuck = self._stalled >= self.rule.patience
        regressed = value < self._best - self.rule.regression
        if stuck or regressed or (closing and self._off_grasp(observation)):
            if self.rule.delay == 0:
                self._take_over(observation, progress)
                return self._expert_action(observation)
            self._countdown = self.rule.delay
        return None

    def _fingers_closing(self, observation: dict[str, np.ndarray]) -> bool:
        """Whether the gripper opening shrank since the last step (by > 1 mm)."""
        opening = float(observation["observation.state"][-1])
        closing = opening < self._opening - 1e-3
        self._opening = opening
        return closing

    def grasp_error(self, observation: dict[str, np.ndarray]) -> float:
        """How far (m) the TCP is from the expert's grasp, across the object's long axis
        (along it, any point is a grasp) and in height; 0 for a task without a grasp."""
        assert self.task is not None and self.config is not None
        grasp = self.task.expert(self.config, self.rng).planned_grasp(observation)
        if grasp is None:
            return 0.0
        view = ObsView(self.task.scene, observation)
        yaw = view.yaw(self.task.object_name)
        axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        offset = view.tcp_pos - grasp[0]
        return float(np.linalg.norm(offset - np.dot(offset, axis) * axis))

    def _off_grasp(self, observation: dict[str, np.ndarray]) -> bool:
        return self.rule.funnel > 0 and self.grasp_error(observation) > self.rule.funnel

    def _take_over(self, observation: dict[str, np.ndarray], progress: Progress) -> None:
        assert self.task is not None and self.config is not None
        self.expert = self.task.expert(self.config, self.rng)
        holding = self.task.object_name if progress.terms.get("grasp", 0.0) > 0.5 else None
        self.expert.take_over(observation, holding, self.rule.correct_within)
        self.takeovers += 1
        self._countdown, self._held = None, 0
        self._best_before = max(self._best, float(sum(progress.terms.values())))

    def _expert_action(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        assert self.expert is not None
        action = np.asarray(self.expert.act(observation), np.float64)
        if self.rule.noise > 0:
            jitter = self.rng.normal(0.0, self.rule.noise, 6) * np.array([1, 1, 1, 5, 5, 5])
            action[:6] += jitter
            self.expert.perturb(jitter[:3], jitter[3:6])
        return action.astype(np.float32)
