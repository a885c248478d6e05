"""ur_rtde in a process of its own: a crash in it cannot take the host's process down.

After a lost connection ur_rtde 1.6.5 reconnects by itself, at once in its receive
thread and in whichever thread's command failed; the two race over the same state and
can end the process with a segmentation fault, before any Python code can say what
happened (about one lost connection in fifteen on the emulator). So the receive and
control interfaces, and the :class:`~twinrl_robot.ur.servo.ServoStream` thread that
feeds the controller at its own rate, live in a child process; the driver reaches them
through :class:`ControllerLink`, one request at a time over a pipe (tens of
microseconds, against a control period of milliseconds). The child is a fresh
interpreter (``python -m twinrl_robot.ur.controller_link``), not a ``multiprocessing``
one, which would import the host's main script again (a script without a ``__main__``
guard would open a second arm). The child watches the host's process: when it is
stopped (Ctrl-Z, ``SIGSTOP``, a debugger) or gone, the child stops sending and the
controller's watchdog stops the arm, as it would for a host streaming by itself. When
the child dies the link says so as a lost connection, the host goes on (the episode
being recorded is closed as it would be after any stop), and
:meth:`ControllerLink.open` starts a fresh child: reconnecting is starting again, not
trusting ur_rtde's own attempt.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import astuple, dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from twinrl_robot.errors import RobotError
from twinrl_robot.ur.servo import ServoStream, SharedControl
from twinrl_robot.ur.tool_frame import ToolFrame

START_TIMEOUT = 30.0  # s for the child to import ur_rtde and connect
STOP_TIMEOUT = 3.0  # s for the child to disconnect before it is killed
HOST_CHECK = 0.005  # s between looks at the host process's state
_CONTROL, _RECEIVE, _STREAM, _CLOSE = "control", "receive", "stream", "close"
_PERIODS, _SNAPSHOT, _HEALTH = "periods", "snapshot", "health"


@dataclass(frozen=True)
class ControllerHealth:
    """Whether the arm can be commanded, read in one request: the receive interface's
    connection, stops and program state, and the servo stream's fault."""

    connected: bool
    emergency_stopped: bool = False
    protective_stopped: bool = False
    runtime_state: int = 0  # the controller's program state (2: running)
    stream_fault: str | None = None  # why the stream stopped sending, if it did
    stream_connection_failed: bool = False  # the stream's fault is a failed connection


def controller_health(receive: Any, stream: Any) -> ControllerHealth:
    """``receive``'s and ``stream``'s state as one :class:`ControllerHealth` (a receive
    interface that is not connected is asked nothing more of the controller)."""
    if not receive.isConnected():
        return ControllerHealth(
            False, stream_fault=stream.fault, stream_connection_failed=stream.connection_failed
        )
    return ControllerHealth(
        True,
        receive.isEmergencyStopped(),
        receive.isProtectiveStopped(),
        receive.getRuntimeState(),
        stream.fault,
        stream.connection_failed,
    )


class ControllerRefused(RobotError):
    """The controller refused ur_rtde's connection (the message says what it said)."""


class LinkLost(RobotError):
    """The child holding ur_rtde has ended (the connection was lost, or ur_rtde crashed
    on losing it); the message says so in one line."""


class ControllerLink:
    """ur_rtde's receive and control interfaces and the servo stream, in a child process.

    ``receive`` and ``control`` call the interfaces' methods by name (a ``RuntimeError``
    in the child comes back as one); ``stream`` is the :class:`ServoStream`'s interface.
    ``servo_pose`` (the controller TCP's pose of joint positions, for servoL) and the
    stream's ``max_speed`` travel to the child with the link.
    """

    def __init__(
        self,
        host: str,
        servo_hz: float,
        servo_pose: ToolFrame | None = None,
        max_speed: float | None = None,
    ) -> None:
        self.host, self.servo_hz, self.servo_pose = host, servo_hz, servo_pose
        self.max_speed = max_speed
        self.receive = _Methods(self, _RECEIVE)
        self.control = _Methods(self, _CONTROL)
        self.stream = StreamProxy(self)
        self.ended: str | None = None  # why the child ended, once it has
        self._lock = threading.Lock()
        self._pipe: Connection | None = None
        self._child: subprocess.Popen | None = None

    def open(self) -> None:
        """Start the child, connect both interfaces and start the stream (it kicks the
        watchdog from here on); a link opened before is closed first."""
        self.close()
        here, there = socket.socketpair()
        child = subprocess.Popen(
            [sys.executable, "-m", __name__, str(there.fileno()), str(os.getpid())],
            pass_fds=(there.fileno(),),
            stdin=subprocess.DEVNULL,
        )
        there.close()
        here = Connection(here.detach())
        self._pipe, self._child, self.ended = here, child, None
        try:  # a child that ended at once breaks the pipe here or at recv
            here.send((self.host, self.servo_hz, self.servo_pose, self.max_speed))
            if here.poll(START_TIMEOUT):
                kind, message = here.recv()
            else:
                kind, message = (
                    "late",
                    (
                        f"the UR controller at {self.host} did not finish connecting in "
                        f"{START_TIMEOUT:g} s; check the controller and the network"
                    ),
                )
        except (EOFError, OSError):
            kind, message = (
                "ended",
                (
                    f"ur_rtde's process ended while connecting to {self.host} (exit status "
                    f"{child.wait()}); see its error above"
                ),
            )
        if kind != "ready":
            self.close()
            raise ControllerRefused(message)

    @property
    def pid(self) -> int | None:
        """The child's process id (``None`` when closed)."""
        return None if self._child is None else self._child.pid

    def snapshot(self, names: tuple[str, ...]) -> list[Any]:
        """The receive interface's ``names`` (getters), read together in one request,
        so they come from the same controller packet or the next."""
        return self.request(_SNAPSHOT, "", names)

    def health(self) -> ControllerHealth:
        """The controller's and the stream's :class:`ControllerHealth`, in one request
        (the loop asks every step, so each extra round trip to the child is a wait for
        its process to be scheduled); a link whose child has ended is not connected."""
        try:
            return ControllerHealth(*self.request(_HEALTH, ""))
        except LinkLost as lost:
            return ControllerHealth(False, stream_fault=str(lost), stream_connection_failed=True)

    def request(self, part: str, name: str, *args: Any) -> Any:
        """Call ``name`` on ``part`` in the child and return what it returned."""
        with self._lock:
            if self._pipe is None or self.ended is not None:
                raise LinkLost(self.ended or "the link to the controller is closed")
            try:
                self._pipe.send((part, name, args))
                ok, value = self._pipe.recv()
            except (EOFError, OSError):
                self.ended = self._why_ended()
                raise LinkLost(self.ended) from None
        if not ok:
            raise RuntimeError(value)
        return value

    def close(self) -> None:
        """Ask the child to stop the stream and disconnect; kill it if it does not."""
        pipe, child = self._pipe, self._child
        self._pipe, self._child = None, None
        if pipe is not None and self.ended is None:
            try:
                pipe.send((_CLOSE, "", ()))
                pipe.poll(STOP_TIMEOUT)
            except OSError:
                pass
        if child is not None:
            try:
                child.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
        if pipe is not None:
            pipe.close()

    def _why_ended(self) -> str:
        child, code = self._child, None
        if child is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = child.wait(1.0)
        how = f" ({signal.Signals(-code).name})" if code is not None and code < 0 else ""
        return (
            f"lost the connection to the controller at {self.host} (ur_rtde's process "
            f"ended{how}); check the network cable and the controller, then acknowledge to "
            "reconnect"
        )


class _Methods:
    """``link.<part>.<method>(*args)`` calls the method in the child."""

    def __init__(self, link: ControllerLink, part: str) -> None:
        self._link, self._part = link, part

    def __getattr__(self, name: str) -> Callable[..., Any]:
        link, part = self._link, self._part
        return lambda *args: link.request(part, name, *args)


class StreamProxy:
    """The :class:`ServoStream` in the child, as the driver uses it (its fault comes with
    :meth:`ControllerLink.health`). Once the child has ended, its commands do nothing."""

    def __init__(self, link: ControllerLink) -> None:
        self._link = link

    def _call(self, name: str, *args: Any) -> Any:
        """What the stream's ``name`` returns in the child, or ``None`` once it has ended."""
        with contextlib.suppress(LinkLost):
            return self._link.request(_STREAM, name, *args)
        return None

    def start(self, q: Any) -> None:
        self._call("start", q)

    def push(self, target: Any, duration: float, until: float) -> None:
        self._call("push", target, duration, until)

    def hold(self, q: Any) -> None:
        self._call("hold", q)

    def stop(self) -> None:
        self._call("stop")

    def resume(self) -> None:
        self._call("resume")

    def silence(self) -> None:
        self._call("silence")

    def close(self) -> None:
        self._call("close")

    @property
    def periods(self) -> list[float]:
        """Seconds between consecutive targets sent (newest last)."""
        return self._call(_PERIODS) or []


class _HostWatch:
    """Whether the host process runs: not stopped (Ctrl-Z, ``SIGSTOP``, a debugger) and
    not gone. Its state is the kernel's (``/proc``), so a host that is busy, however long
    it holds its interpreter, is never taken for a stopped one."""

    def __init__(self, pid: int) -> None:
        self._stat = Path(f"/proc/{pid}/stat")
        self._alive, self._looked = True, 0.0

    def alive(self) -> bool:
        now = time.monotonic()
        if now - self._looked >= HOST_CHECK:
            self._looked = now
            try:
                state = self._stat.read_text().rsplit(")", 1)[1].split()[0]
            except (OSError, IndexError):
                state = "X"  # gone
            self._alive = state not in ("T", "t", "Z", "X")
        return self._alive


def _serve(pipe: Connection, host_pid: int) -> None:
    """The child: connect, stream, and answer requests until told to close or the host
    goes (the stream then stops, and the watchdog stops the controller's program)."""
    import rtde_control
    import rtde_receive

    host, servo_hz, servo_pose, max_speed = pipe.recv()

    try:
        receive = rtde_receive.RTDEReceiveInterface(host, servo_hz)
        control = SharedControl(rtde_control.RTDEControlInterface(host, servo_hz))
    except RuntimeError as err:
        message = str(err).splitlines()[0].removeprefix("ur_rtde: ")
        pipe.send(
            (
                "refused",
                f"the UR controller at {host} refused the connection: {message}; put the "
                "pendant in Remote Control and check that no other program drives the arm",
            )
        )
        return
    stream = ServoStream(
        control,
        servo_hz,
        None if servo_pose is None else servo_pose.pose,
        host_alive=_HostWatch(host_pid).alive,
        max_speed=max_speed,
    )
    stream.open()
    pipe.send(("ready", ""))
    parts = {_RECEIVE: receive, _CONTROL: control, _STREAM: stream}
    try:
        while True:
            try:
                part, name, args = pipe.recv()
            except (EOFError, OSError):
                break
            if part == _CLOSE:
                break
            try:
                if part == _HEALTH:
                    # A plain tuple: this module is ``__main__`` here, so its classes
                    # would not unpickle in the host.
                    value = astuple(controller_health(receive, stream))
                elif part == _SNAPSHOT:
                    value = [getattr(receive, getter)() for getter in args[0]]
                elif part == _STREAM and name == _PERIODS:
                    value = list(stream.periods)
                else:
                    value = getattr(parts[part], name)(*args)
                pipe.send((True, value))
            except RuntimeError as err:
                pipe.send((False, str(err)))
    finally:
        stream.close()
        control.disconnect()
        receive.disconnect()


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])), int(sys.argv[2]))
