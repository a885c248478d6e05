"""Grippers a UR cell carries, behind one small protocol.

* :class:`RobotiqGripper`: a Robotiq 2F-85 or 2F-140 through the Robotiq URCap's socket
  on the controller (port 63352): text lines ``SET <VAR> <value>`` answered ``ack`` and
  ``GET <VAR>`` answered ``<VAR> <value>``; ``POS`` 0 (open) to 255 (closed).
* :class:`DigitalGripper`: a gripper switched by one of the controller's digital outputs
  (through ``ur_rtde``'s ``RTDEIOInterface``).
* :class:`NoGripper`: the arm carries none; the gripper command is ignored.

Every gripper takes the episode contract's command in [0, 1] (0 open, 1 closed) and
reports its measured opening in metres.
"""

from __future__ import annotations

import socket
import threading
import time
from typing import Protocol, runtime_checkable

from twinrl_robot.errors import RobotError

STROKES = {"robotiq_2f85": 0.085, "robotiq_2f140": 0.140}  # m, fully open
ACTIVATION_TIMEOUT = 5.0  # s
POLL_PERIOD = 0.02  # s between reads of a Robotiq's position: five a 10 Hz control period


class GripperError(RobotError):
    """The gripper cannot be reached or does not respond as its protocol says."""


@runtime_checkable
class Gripper(Protocol):
    """A gripper commanded in [0, 1] (0 open, 1 closed) that reports its opening (m)."""

    def command(self, closure: float) -> None: ...

    def opening(self) -> float: ...

    def describe(self) -> str: ...

    def close(self) -> None: ...


class NoGripper:
    """The arm carries no gripper."""

    def command(self, closure: float) -> None:
        return None

    def opening(self) -> float:
        return 0.0

    def describe(self) -> str:
        return "none"

    def close(self) -> None:
        return None


class RobotiqGripper:
    """A Robotiq 2F gripper through the URCap socket (see the module docstring).

    The socket is served by a thread of its own, so that the control loop never waits
    for an answer: a round trip takes a millisecond or two, and at times (a controller
    or a host under load) over a control period. :meth:`command` hands the thread the
    newest position (the newest command wins; it is sent when it changes by at least one
    of the gripper's 255 steps, so a 10 Hz policy does not flood the socket) and
    :meth:`opening` reads the newest of the positions it asks for every
    :data:`POLL_PERIOD`. What goes wrong in the thread (an error answer, a lost
    connection, no answer for ``timeout`` seconds) is raised by the next call.
    """

    def __init__(
        self, host: str, *, port: int = 63352, kind: str = "robotiq_2f85", timeout: float = 2.0
    ) -> None:
        if kind not in STROKES:
            raise GripperError(f"unknown Robotiq gripper '{kind}': use one of {list(STROKES)}")
        self.kind, self.stroke = kind, STROKES[kind]
        self.address = f"{host}:{port}"
        try:
            self._socket = socket.create_connection((host, port), timeout=timeout)
        except OSError as err:
            raise GripperError(
                f"cannot reach the Robotiq gripper at {self.address} ({err.strerror or err}); "
                "check that the Robotiq URCap is installed and the gripper is connected"
            ) from None
        self._socket.settimeout(timeout)
        self.timeout = timeout
        self._buffer = b""
        self._sent_position: int | None = None
        self._wanted: int | None = None  # the newest commanded position, not yet sent
        self._fault: GripperError | None = None
        self._wake, self._closing = threading.Event(), threading.Event()
        self._activate()
        self._position, self._read_at = self._get("POS"), time.monotonic()
        self._thread = threading.Thread(target=self._serve, name="robotiq-gripper", daemon=True)
        self._thread.start()

    def _activate(self) -> None:
        if self._get("STA") == 3:
            return
        self._set(ACT=0)
        self._set(ACT=1)
        deadline = time.monotonic() + ACTIVATION_TIMEOUT
        while self._get("STA") != 3:
            if time.monotonic() > deadline:
                raise GripperError(
                    f"the Robotiq gripper at {self.address} did not finish activating in "
                    f"{ACTIVATION_TIMEOUT:g} s; check its cable and the URCap's status"
                )
            time.sleep(0.02)
        self._set(GTO=1, SPE=255, FOR=150)

    def command(self, closure: float) -> None:
        self._raise_fault()
        self._wanted = round(min(max(float(closure), 0.0), 1.0) * 255)
        self._wake.set()

    def opening(self) -> float:
        self._raise_fault()
        age = time.monotonic() - self._read_at
        if age > self.timeout:
            raise GripperError(
                f"the Robotiq gripper at {self.address} has not answered for {age:.1f} s; "
                "check its cable and the URCap's status"
            )
        return self.stroke * (1.0 - self._position / 255.0)

    def describe(self) -> str:
        return f"{self.kind} at {self.address}"

    def close(self) -> None:
        self._closing.set()
        self._wake.set()
        self._thread.join(timeout=self.timeout + 1.0)
        self._socket.close()

    def _serve(self) -> None:
        """Send the newest command when it changed, then read the position; again every
        :data:`POLL_PERIOD` or as soon as a command comes."""
        while not self._closing.is_set():
            self._wake.clear()  # a command from here on is sent without waiting
            try:
                wanted = self._wanted
                if wanted is not None and wanted != self._sent_position:
                    self._set(POS=wanted, GTO=1)
                    self._sent_position = wanted
                self._position, self._read_at = self._get("POS"), time.monotonic()
            except GripperError as err:
                if not self._closing.is_set():
                    self._fault = err
                return
            self._wake.wait(POLL_PERIOD)

    def _raise_fault(self) -> None:
        if self._fault is not None:
            raise self._fault

    def _set(self, **values: int) -> None:
        line = "SET " + " ".join(f"{k} {int(v)}" for k, v in values.items())
        reply = self._exchange(line)
        if reply != "ack":
            raise GripperError(
                f"the Robotiq gripper at {self.address} answered {reply!r} to {line!r}"
            )

    def _get(self, variable: str) -> int:
        reply = self._exchange(f"GET {variable}")
        name, _, value = reply.partition(" ")
        if name != variable or not value.strip().lstrip("-").isdigit():
            raise GripperError(
                f"the Robotiq gripper at {self.address} answered {reply!r} to GET {variable}"
            )
        return int(value)

    def _exchange(self, line: str) -> str:
        """One request and its answer (the socket is the serving thread's alone once it
        runs)."""
        try:
            self._socket.sendall(line.encode() + b"\n")
            while b"\n" not in self._buffer:
                chunk = self._socket.recv(1024)
                if not chunk:
                    raise GripperError(
                        f"the Robotiq gripper at {self.address} closed the connection"
                    )
                self._buffer += chunk
        except OSError as err:
            raise GripperError(
                f"lost the Robotiq gripper at {self.address} ({err.strerror or err})"
            ) from None
        reply, _, self._buffer = self._buffer.partition(b"\n")
        return reply.decode(errors="replace").strip()


class DigitalGripper:
    """A gripper that closes while a digital output is high (``RTDEIOInterface``)."""

    def __init__(self, io: object, output: int, stroke: float = 0.085) -> None:
        self._io, self.output, self.stroke = io, output, stroke
        self._closed: bool | None = None

    def command(self, closure: float) -> None:
        closed = closure >= 0.5
        if closed != self._closed:
            if not self._io.setStandardDigitalOut(self.output, closed):  # type: ignore[attr-defined]
                raise GripperError(f"the controller refused to set digital output {self.output}")
            self._closed = closed

    def opening(self) -> float:
        """A switched gripper has no position sensor: its commanded state stands in."""
        return 0.0 if self._closed else self.stroke

    def describe(self) -> str:
        return f"digital output {self.output}"

    def close(self) -> None:
        return None
