"""What every teleop device gives: its latest axes and held buttons, read in a thread
of its own with the time of its last input, and a clear error when it goes away."""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from twinrl_robot.errors import RobotError
from twinrl_sim.tasks import Task, TaskConfig


class TeleopError(RobotError):
    """A teleop device is missing, refused or went away; the message says what to do."""


@dataclass(frozen=True)
class DeviceState:
    """A device at one moment: each axis in [-1, 1], the buttons held, and when the
    device last reported (``time.monotonic()``; 0: never)."""

    axes: Mapping[str, float] = field(default_factory=dict)
    buttons: frozenset[str] = frozenset()
    stamp: float = 0.0


@runtime_checkable
class InputDevice(Protocol):
    """A teleop device. ``read`` returns its latest state without waiting and raises
    :class:`TeleopError` once it is gone (unplugged, closed). ``observation`` is what the
    person sees at this step: a scripted person reads it, a real device ignores it.
    ``continuous``: the device reports while deflected, so silence with an axis deflected
    means it stopped talking (the arm then holds)."""

    kind: str
    continuous: bool

    def read(self, observation: Mapping[str, np.ndarray] | None = None) -> DeviceState: ...

    def episode(self, task: Task, config: TaskConfig) -> None:
        """An episode of ``task`` from ``config`` starts (a scripted person plans it)."""
        ...

    def close(self) -> None: ...


class ReaderThread:
    """Runs ``poll`` (one blocking read with a short timeout) in a daemon thread until
    closed; an exception from it ends the thread and is kept as the device's error."""

    def __init__(self, name: str, poll: Callable[[], None], gone: Callable[[BaseException], str]):
        self._poll, self._gone = poll, gone
        self._stop = threading.Event()
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._poll()
            except Exception as err:  # the device is gone: say why at the next read
                if not self._stop.is_set():
                    self.error = self._gone(err)
                return

    def check(self) -> None:
        if self.error is not None:
            raise TeleopError(self.error)

    def stop(self) -> None:
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=1.0)


class LatestState:
    """A device's state, updated by its reader thread and read by the control loop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._axes: dict[str, float] = {}
        self._buttons: set[str] = set()
        self._pressed: set[str] = set()  # pressed since the last read, even if released
        self._stamp = 0.0

    def update(
        self,
        axes: Mapping[str, float] | None = None,
        pressed: set[str] | frozenset[str] = frozenset(),
        released: set[str] | frozenset[str] = frozenset(),
    ) -> None:
        with self._lock:
            if axes:
                self._axes.update({k: float(np.clip(v, -1.0, 1.0)) for k, v in axes.items()})
            self._buttons |= pressed
            self._pressed |= pressed
            self._buttons -= released
            self._stamp = time.monotonic()

    def snapshot(self) -> DeviceState:
        """The state now; a button pressed and released between two reads still counts
        as held once, so a quick tap is never lost."""
        with self._lock:
            buttons = frozenset(self._buttons | self._pressed)
            self._pressed = set()
            return DeviceState(dict(self._axes), buttons, self._stamp)


class ThreadedDevice(ABC):
    """A device whose reader thread polls it into a :class:`LatestState`: subclasses set
    ``kind`` and ``continuous``, call :meth:`_start`, and give ``_poll`` (one read of the
    device) and ``_release`` (close it)."""

    kind: str
    continuous: bool

    def _start(self, name: str, gone: str) -> None:
        self._state = LatestState()
        self._reader = ReaderThread(name, self._poll, lambda err: gone)

    @abstractmethod
    def _poll(self) -> None: ...

    @abstractmethod
    def _release(self) -> None: ...

    def read(self, observation: Mapping[str, np.ndarray] | None = None) -> DeviceState:
        self._reader.check()
        return self._state.snapshot()

    def episode(self, task: Task, config: TaskConfig) -> None:  # noqa: B027 (a real no-op)
        """A device plans nothing."""

    def close(self) -> None:
        self._reader.stop()
        self._release()
