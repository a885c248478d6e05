"""A teleop device with its map: per control step, the 7-D action a person commands
and the marks they pressed; as an action source (recording) or an operator (real RL).

The **deadman**: the arm moves only while the person deflects the device (and holds
its deadman button, where the map names one); no input, a released button or a device
that stopped reporting gives a zero motion, so the arm holds where it is. A device that
goes away mid-episode holds the arm too and says so in :attr:`Teleop.lost`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from twinrl_robot.teleop.device import DeviceState, InputDevice, TeleopError
from twinrl_robot.teleop.settings import DeviceMap
from twinrl_sim.tasks import Progress, Task, TaskConfig

STALE = 0.5  # s without a report from a deflected continuous device before it counts as still
CLOSED_BELOW = 0.9  # of the widest opening seen: a takeover starts with the gripper closed


@dataclass(frozen=True)
class TeleopStep:
    """One step of a person at a device: the action, and the events they raised."""

    action: np.ndarray  # float32[7]: the motion (zero when holding) and the gripper command
    events: tuple[str, ...]
    moving: bool


class Teleop:
    """``device`` read through ``device_map`` (see the module docstring)."""

    def __init__(self, device: InputDevice, device_map: DeviceMap) -> None:
        self.device, self.map = device, device_map
        self._event_of = {button: event for event, button in device_map.buttons.items()}
        self._scale = np.array([device_map.translation] * 3 + [device_map.rotation] * 3)
        self.lost: str | None = None
        self.reset()

    @property
    def kind(self) -> str:
        return self.device.kind

    def reset(self, gripper: float = 0.0) -> None:
        """A new episode: gripper as given, the policy in control, no button held."""
        self.gripper = float(gripper)
        self.in_control = False
        self._held: frozenset[str] = frozenset()

    def step(self, observation: Mapping[str, np.ndarray] | None = None) -> TeleopStep:
        try:
            state = self.device.read(observation)
        except TeleopError as err:
            self.lost = str(err)
            return TeleopStep(self.action_with(np.zeros(6)), (), False)
        pressed = state.buttons - self._held
        self._held = state.buttons
        events = tuple(self._event_of[b] for b in sorted(pressed) if b in self._event_of)
        for event in events:
            if event == "gripper":
                self.gripper = 0.0 if self.gripper > 0.5 else 1.0
            elif event == "takeover":
                self.in_control = not self.in_control
        motion = self._motion(state)
        return TeleopStep(self.action_with(motion), events, bool(np.any(motion)))

    def _motion(self, state: DeviceState) -> np.ndarray:
        if self.map.deadman is not None and self.map.deadman not in state.buttons:
            return np.zeros(6)
        values = np.array([_axis(state.axes, spec) for spec in self.map.axes])
        stale = time.monotonic() - state.stamp > STALE
        if self.device.continuous and stale:
            return np.zeros(6)
        band = self.map.deadband
        magnitude = np.clip((np.abs(values) - band) / (1.0 - band), 0.0, 1.0)
        return np.sign(values) * magnitude * self._scale

    def action_with(self, motion: np.ndarray) -> np.ndarray:
        """The 7-D action of ``motion`` (6-D) with the gripper as commanded now."""
        return np.concatenate([motion, [self.gripper]]).astype(np.float32)

    def close(self) -> None:
        self.device.close()


def _axis(axes: Mapping[str, float], spec: str) -> float:
    if spec == "none":
        return 0.0
    value = float(axes.get(spec.removeprefix("-"), 0.0))
    return -value if spec.startswith("-") else value


class TeleopSource:
    """A person driving every step of an episode (recording): an action source whose
    events the recorder collects with :meth:`take_events`."""

    def __init__(self, teleop: Teleop) -> None:
        self.teleop = teleop
        self._events: list[str] = []
        self.observation: dict[str, np.ndarray] | None = None  # what the person last saw

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.teleop.reset()
        self.teleop.device.episode(task, config)

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        self.observation = observation
        step = self.teleop.step(observation)
        self._events += step.events
        return step.action

    def interrupted(self) -> None:
        """Nobody takes the controls from the person."""

    def take_events(self) -> list[str]:
        events, self._events = self._events, []
        return events


class GripperAsLeft:
    """The gripper command a takeover starts with, as the policy left the fingers: closed
    when they open less than :data:`CLOSED_BELOW` of their widest this episode."""

    def __init__(self) -> None:
        self.widest = 0.0

    def see(self, observation: Mapping[str, np.ndarray]) -> float:
        """Take this step's opening into account; the command a takeover now starts with."""
        opening = float(observation["observation.state"][-1])
        self.widest = max(self.widest, opening)
        return float(opening < CLOSED_BELOW * self.widest)


class TeleopOperator:
    """A person at a device as the RL loop's :class:`~twinrl_robot.operator.Operator`:
    their ``takeover`` button takes the controls from the policy and hands them back;
    while they hold them, their device drives, starting with the gripper as the policy
    left it (closed when it opens less than :data:`CLOSED_BELOW` of its widest this
    episode). Judges nothing: it works on a real cell."""

    judges_progress = False

    def __init__(self, teleop: Teleop) -> None:
        self.teleop = teleop
        self.takeovers = 0
        self._events: list[str] = []

    @property
    def in_control(self) -> bool:
        return self.teleop.in_control

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.teleop.reset()
        self.teleop.device.episode(task, config)
        self.takeovers = 0
        self._gripper = GripperAsLeft()

    def intervene(
        self, observation: dict[str, np.ndarray], progress: Progress | None
    ) -> np.ndarray | None:
        as_left = self._gripper.see(observation)
        was = self.teleop.in_control
        step = self.teleop.step(observation)
        self._events += step.events
        if self.teleop.in_control and not was:
            self.takeovers += 1
            self.teleop.gripper = as_left
            step = TeleopStep(self.teleop.action_with(step.action[:6]), step.events, step.moving)
        return step.action if self.teleop.in_control else None

    def take_events(self) -> list[str]:
        events, self._events = self._events, []
        return events
