"""Keys from the terminal the recorder runs in (no display needed): the recording's
marks for every device, and a keyboard teleop device.

The terminal is put in cbreak mode (keys arrive one by one, unechoed; Ctrl-C still
interrupts) and restored on close. Terminals send no key releases: a key counts as held
for :data:`FIRST_HOLD` s after it is pressed (the terminal's repeat delay) and
:data:`REPEAT_HOLD` s after each repeat, so holding a key moves the arm and letting go
stops it within a tenth of a second of the repeats stopping.
"""

from __future__ import annotations

import os
import queue
import select
import sys
import termios
import threading
import time
import tty
from collections.abc import Mapping

import numpy as np

from twinrl_robot.teleop.device import DeviceState, ReaderThread, TeleopError
from twinrl_sim.tasks import Task, TaskConfig

FIRST_HOLD = 0.55  # s a fresh key press counts as held (covers the terminal's repeat delay)
REPEAT_HOLD = 0.12  # s each repeat extends it
SEQUENCES = {
    b"\x1b[A": "up",
    b"\x1b[B": "down",
    b"\x1b[C": "right",
    b"\x1b[D": "left",
    b"\x1b[5~": "pageup",
    b"\x1b[6~": "pagedown",
    b"\r": "enter",
    b"\n": "enter",
    b" ": "space",
    b"\x7f": "backspace",
    b"\x08": "backspace",
    b"\t": "tab",
}
KEY_AXES = {
    "i": ("x", 1.0),
    "k": ("x", -1.0),
    "j": ("y", 1.0),
    "l": ("y", -1.0),
    "u": ("z", 1.0),
    "o": ("z", -1.0),
    ",": ("rx", 1.0),
    ".": ("rx", -1.0),
    "up": ("ry", 1.0),
    "down": ("ry", -1.0),
    "left": ("rz", 1.0),
    "right": ("rz", -1.0),
}
"""The keyboard device's motion keys: i/k forward and back (x), j/l left and right (y),
u/o up and down (z); the arrows tilt (ry) and turn (rz), comma and full stop roll (rx)."""


def decode(data: bytes) -> list[str]:
    """Key names in a burst of terminal bytes (escape sequences whole)."""
    keys, i = [], 0
    while i < len(data):
        for sequence, name in SEQUENCES.items():
            if data.startswith(sequence, i):
                keys.append(name)
                i += len(sequence)
                break
        else:
            if data[i] == 0x1B:  # an escape sequence we do not use: skip it whole
                end = i + 1
                if end < len(data) and data[end] in b"[O":
                    end += 1
                    while end < len(data) and not 0x40 <= data[end] <= 0x7E:
                        end += 1
                    end += 1
                keys.append("esc" if end == i + 1 else "?")
                i = end
                continue
            keys.append(chr(data[i]) if data[i] >= 0x20 else "?")
            i += 1
    return keys


class TerminalKeys:
    """Key presses from a terminal (``fd``: standard input by default), each with the
    time it arrived, delivered to every subscriber's queue."""

    def __init__(self, fd: int | None = None) -> None:
        self.fd = sys.stdin.fileno() if fd is None else fd
        if not os.isatty(self.fd):
            raise TeleopError(
                "the keyboard is read from a terminal, and standard input is not one; run the "
                "recording in a terminal (not piped), or choose another `teleop`"
            )
        self._saved = termios.tcgetattr(self.fd)
        tty.setcbreak(self.fd)
        self._subscribers: list[queue.SimpleQueue[tuple[str, float]]] = []
        self._lock = threading.Lock()
        self.typing = False  # a line (a note) is being typed: the keyboard device ignores keys
        self._reader = ReaderThread("terminal keys", self._poll, lambda err: f"terminal: {err}")

    def subscribe(self) -> queue.SimpleQueue[tuple[str, float]]:
        keys: queue.SimpleQueue[tuple[str, float]] = queue.SimpleQueue()
        with self._lock:
            self._subscribers.append(keys)
        return keys

    def _poll(self) -> None:
        ready, _, _ = select.select([self.fd], [], [], 0.05)
        if not ready:
            return
        data = os.read(self.fd, 64)
        if not data:
            raise EOFError("the terminal closed")
        now = time.monotonic()
        with self._lock:
            for key in decode(data):
                for subscriber in self._subscribers:
                    subscriber.put((key, now))

    def check(self) -> None:
        """Raise :class:`TeleopError` if the terminal went away."""
        self._reader.check()

    def close(self) -> None:
        self._reader.stop()
        termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)


class Keyboard:
    """The terminal's keys as an :class:`~twinrl_robot.teleop.device.InputDevice`: the
    motion keys (:data:`KEY_AXES`) give full deflection while held; every key is also a
    button of its own name (``space``, ``t``), held as long."""

    kind = "keyboard"
    continuous = False  # held keys are timed here, not by reports

    def __init__(self, keys: TerminalKeys) -> None:
        self.keys = keys
        self._queue = keys.subscribe()
        self._until: dict[str, float] = {}

    def read(self, observation: Mapping[str, np.ndarray] | None = None) -> DeviceState:
        self.keys.check()
        pressed: set[str] = set()
        while True:
            try:
                key, at = self._queue.get_nowait()
            except queue.Empty:
                break
            if self.keys.typing:
                continue
            repeat = self._until.get(key, 0.0) >= at
            self._until[key] = at + (REPEAT_HOLD if repeat else FIRST_HOLD)
            pressed.add(key)
        now = time.monotonic()
        held = {key for key, until in self._until.items() if until >= now} | pressed
        axes: dict[str, float] = {}
        for key in held:
            if key in KEY_AXES:
                axis, sign = KEY_AXES[key]
                axes[axis] = float(np.clip(axes.get(axis, 0.0) + sign, -1.0, 1.0))
        return DeviceState(axes, frozenset(held), now)

    def episode(self, task: Task, config: TaskConfig) -> None:
        """Keys plan nothing."""

    def close(self) -> None:
        """The terminal belongs to the recording; it closes it."""
