"""A gamepad through Linux evdev (``/dev/input/event*``), no display needed.

Axes and buttons keep the kernel's names (``ABS_X``, ``BTN_SOUTH``; a button answers
to every alias the kernel gives it, so ``BTN_A`` is ``BTN_SOUTH``). Sticks are scaled
to [-1, 1] around their centre from the device's own ranges, triggers
(``ABS_Z``/``ABS_RZ``/``ABS_GAS``/``ABS_BRAKE``) to [0, 1]. The person needs read access to
the event node (the ``input`` group). A :class:`RecordedEvents` source plays recorded
events back, as a virtual ``uinput`` pad does where the kernel offers one.
"""

from __future__ import annotations

import select
import time
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from twinrl_robot.teleop.device import TeleopError, ThreadedDevice

READ_TIMEOUT = 0.05  # s, one wait for events
TRIGGERS = ("ABS_Z", "ABS_RZ", "ABS_GAS", "ABS_BRAKE")
UNPLUGGED = (
    "the gamepad went away (unplugged, or its battery or radio dropped); the arm holds. "
    "Reconnect it and start the recording again: the session continues"
)


class EventSource(Protocol):
    """Where gamepad events come from: ``(type, code, value)`` triples, and each axis's
    range (``(min, max)`` by code)."""

    name: str

    def read_events(self, timeout: float) -> list[tuple[int, int, int]]: ...

    def axis_range(self, code: int) -> tuple[int, int]: ...

    def close(self) -> None: ...


class EvdevSource:
    """An evdev input device by path."""

    def __init__(self, path: str) -> None:
        import evdev

        try:
            self._device = evdev.InputDevice(path)
        except OSError as err:
            raise TeleopError(
                f"cannot open the gamepad at {path} ({err.strerror or err}); add your user to "
                "the input group or choose another `teleop`"
            ) from None
        self.name = self._device.name

    def read_events(self, timeout: float) -> list[tuple[int, int, int]]:
        ready, _, _ = select.select([self._device.fd], [], [], timeout)
        if not ready:
            return []
        try:
            return [(e.type, e.code, e.value) for e in self._device.read()]
        except BlockingIOError:
            return []

    def axis_range(self, code: int) -> tuple[int, int]:
        info = self._device.absinfo(code)
        return info.min, info.max

    def close(self) -> None:
        self._device.close()


class RecordedEvents:
    """Recorded events ``[(seconds since the first, type, code, value)]`` played back in
    real time from construction; then silent, or gone (``unplug_at_end``)."""

    name = "recorded gamepad"

    def __init__(
        self,
        events: Sequence[tuple[float, int, int, int]],
        ranges: Mapping[int, tuple[int, int]],
        *,
        unplug_at_end: bool = False,
    ) -> None:
        self.events, self.ranges, self.unplug_at_end = list(events), dict(ranges), unplug_at_end
        self._start = time.monotonic()
        self._next = 0

    def read_events(self, timeout: float) -> list[tuple[int, int, int]]:
        if self._next >= len(self.events):
            if self.unplug_at_end:
                raise OSError(19, "No such device")
            time.sleep(timeout)
            return []
        due = self._start + self.events[self._next][0]
        time.sleep(min(timeout, max(0.0, due - time.monotonic())))
        now, out = time.monotonic() - self._start, []
        while self._next < len(self.events) and self.events[self._next][0] <= now:
            out.append(self.events[self._next][1:])
            self._next += 1
        return out

    def axis_range(self, code: int) -> tuple[int, int]:
        return self.ranges[code]

    def close(self) -> None:
        self._next = len(self.events)


class Gamepad(ThreadedDevice):
    """A gamepad as an :class:`~twinrl_robot.teleop.device.InputDevice`."""

    kind = "gamepad"
    continuous = False  # evdev reports changes only: a held stick is silent

    def __init__(self, source: EventSource) -> None:
        from evdev import ecodes

        self.source, self._ecodes = source, ecodes
        self._ranges: dict[int, tuple[int, int]] = {}
        self._start("gamepad", UNPLUGGED)

    def _poll(self) -> None:
        ecodes = self._ecodes
        for kind, code, value in self.source.read_events(READ_TIMEOUT):
            if kind == ecodes.EV_ABS:
                name = ecodes.ABS.get(code)
                if isinstance(name, str):
                    self._state.update({name: self._scaled(name, code, value)})
            elif kind == ecodes.EV_KEY and value in (0, 1):
                names = ecodes.keys.get(code, ())
                names = frozenset([names] if isinstance(names, str) else names)
                self._state.update(
                    pressed=names if value else frozenset(),
                    released=names if not value else frozenset(),
                )

    def _scaled(self, name: str, code: int, value: int) -> float:
        if code not in self._ranges:
            self._ranges[code] = self.source.axis_range(code)
        low, high = self._ranges[code]
        if high <= low:
            return 0.0
        if name in TRIGGERS:
            return (value - low) / (high - low)
        return 2.0 * (value - low) / (high - low) - 1.0

    def _release(self) -> None:
        self.source.close()


def open_gamepad(path: str | None = None) -> Gamepad:
    """The gamepad at ``path``, or the first evdev device with a gamepad's south button
    and sticks; one line on why there is none."""
    import evdev

    if path is not None:
        return Gamepad(EvdevSource(path))
    for candidate in evdev.list_devices():
        try:
            device: Any = evdev.InputDevice(candidate)
        except OSError:
            continue
        capabilities = device.capabilities()
        keys = capabilities.get(evdev.ecodes.EV_KEY, [])
        axes = [code for code, _ in capabilities.get(evdev.ecodes.EV_ABS, [])]
        device.close()
        if evdev.ecodes.BTN_SOUTH in keys and evdev.ecodes.ABS_X in axes:
            return Gamepad(EvdevSource(candidate))
    raise TeleopError(
        "no gamepad found among /dev/input/event* (none plugged in, or your user cannot read "
        "them: add it to the input group); plug one in or choose another `teleop`"
    )
