"""A scripted person at a virtual device: the task's scripted expert deflects the
device's axes and presses its buttons, so recording and real RL with a person run end
to end where no person is (CI, the plant, the emulator).

It needs to see the objects and whether the task succeeded, which only a simulated or
emulated cell lends (the privileged channel); on a real cell a person is at the device.
Each episode it starts, drives the expert's motion through the device map (scaling,
axis map, the deadman's zero when it lets go), presses ``gripper`` when the expert's
gripper command changes, and, when the task succeeds or the expert's plan is done,
presses the mark its script gives that episode (``success`` by default; ``failure`` or
``discard`` to exercise those paths).

In real RL it ``watches`` the policy instead, as the simulated operator's rule says
(:class:`~twinrl_robot.operator.OperatorRule`): it presses ``takeover`` when the rule
takes the controls, drives the rule's expert through the device, and presses
``takeover`` again to hand back.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from twinrl_robot.operator import OperatorRule, SimulatedOperator
from twinrl_robot.robot import Privileged
from twinrl_robot.teleop.device import DeviceState, TeleopError
from twinrl_robot.teleop.settings import ACTION_AXES, DeviceMap
from twinrl_robot.teleop.teleop import GripperAsLeft
from twinrl_sim.tasks import Task, TaskConfig
from twinrl_sim.tasks.expert import GRIPPER_CLOSED, ScriptedExpert


class ScriptedPerson:
    """The scripted expert at a virtual device (see the module docstring).

    Args:
        privileged: the cell's ground truth (plant, twin or emulator).
        device_map: the map the recording reads this device through (its buttons are
            pressed by event name).
        marks: per episode in turn, the mark pressed at its end (then ``success``).
        noise: hand jitter, m per step (rotations: 5x, in rad), which the expert corrects.
        seed: seeds the expert's grasps and the jitter.
        watch: in real RL, when to take over from the policy and hand back (the
            simulated operator's rule, with its own jitter); ``None`` drives every step.
    """

    kind = "scripted"
    continuous = False

    def __init__(
        self,
        privileged: Privileged | None,
        device_map: DeviceMap,
        *,
        marks: Sequence[str] = (),
        noise: float = 0.002,
        seed: int = 0,
        watch: OperatorRule | None = None,
    ) -> None:
        if privileged is None:
            raise TeleopError(
                "the scripted person sees the objects through the cell's ground truth, which a "
                "real cell does not have; use it on the plant or the emulator, or choose a "
                "device a person holds (--teleop spacemouse, gamepad, keyboard)"
            )
        self.privileged, self.map = privileged, device_map
        self.marks, self.noise = list(marks), noise
        self.rng = np.random.default_rng(seed)
        self._expert: ScriptedExpert | None = None
        self._gripper = 0.0
        self._marked = False
        self._stamp = 0.0
        self._watcher = None if watch is None else SimulatedOperator(watch, seed=seed)
        self._holding = False  # watching: whether it has the controls
        self._as_left = GripperAsLeft()

    def episode(self, task: Task, config: TaskConfig) -> None:
        self._expert = task.expert(config, self.rng)
        self._gripper, self._marked = 0.0, False
        if self._watcher is not None:
            self._watcher.reset(task, config)
            self._holding, self._as_left = False, GripperAsLeft()

    def read(self, observation: Mapping[str, np.ndarray] | None = None) -> DeviceState:
        self._stamp += 1.0
        if observation is None or self._expert is None:  # the cell is set up: start
            return DeviceState({}, self._button("start"), self._stamp)
        if self._marked:
            return DeviceState({}, frozenset(), self._stamp)
        if self.privileged.success or self._expert.done:
            self._marked = True
            mark = self.marks.pop(0) if self.marks else "success"
            return DeviceState({}, self._button(mark), self._stamp)
        if self._watcher is not None:
            return self._watch(observation)
        action = np.asarray(self._expert.act(dict(observation)), np.float64)
        if self.noise > 0:
            shake = self.rng.normal(0.0, self.noise, 6) * np.array([1, 1, 1, 5, 5, 5])
            action[:6] += shake
            self._expert.perturb(shake[:3], shake[3:])
        buttons: frozenset[str] = frozenset()
        closing = float(action[6] >= GRIPPER_CLOSED)
        if closing != self._gripper:
            self._gripper = closing
            buttons = self._button("gripper")
        return DeviceState(self._deflection(action[:6]), buttons, self._stamp)

    def _watch(self, observation: Mapping[str, np.ndarray]) -> DeviceState:
        """Real RL: take over, drive and hand back as the watcher's rule says."""
        assert self._watcher is not None
        as_left = self._as_left.see(observation)  # what the takeover will start with
        action = self._watcher.intervene(dict(observation), self.privileged.progress)
        if action is None:
            released = self._holding
            self._holding = False
            return DeviceState(
                {}, self._button("takeover") if released else frozenset(), self._stamp
            )
        buttons: frozenset[str] = frozenset()
        if not self._holding:  # the device's takeover starts from the gripper as it is
            self._holding = True
            self._gripper = as_left
            buttons = self._button("takeover")
        elif float(action[6] >= GRIPPER_CLOSED) != self._gripper:
            self._gripper = float(action[6] >= GRIPPER_CLOSED)
            buttons = self._button("gripper")
        return DeviceState(self._deflection(np.asarray(action[:6])), buttons, self._stamp)

    def _deflection(self, motion: np.ndarray) -> dict[str, float]:
        """The axes that command ``motion`` through the map (the map's inverse)."""
        scale = [self.map.translation] * 3 + [self.map.rotation] * 3
        axes: dict[str, float] = {}
        for i, (spec, _) in enumerate(zip(self.map.axes, ACTION_AXES, strict=True)):
            if spec == "none":
                continue
            sign = -1.0 if spec.startswith("-") else 1.0
            axes[spec.removeprefix("-")] = float(np.clip(sign * motion[i] / scale[i], -1, 1))
        return axes

    def _button(self, event: str) -> frozenset[str]:
        button = self.map.buttons.get(event)
        return frozenset([button]) if button is not None else frozenset()

    def close(self) -> None:
        """Nothing to release."""
