"""The Robotiq gripper's socket served off the control loop: a slow answer never holds
the loop up, and what goes wrong reaches it as one line."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from twinrl_robot.ur.gripper import POLL_PERIOD, GripperError, RobotiqGripper


class URCap:
    """A Robotiq URCap socket on localhost: ``SET`` answered ``ack``, ``GET`` with the
    variable's value; ``delay`` s before each answer once activated; ``silent``: no
    answer at all; ``hang_up``: the connection closed."""

    def __init__(self) -> None:
        self.values = {"STA": 3, "POS": 0}
        self.sets: list[str] = []
        self.delay, self.silent, self.hang_up = 0.0, False, threading.Event()
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        connection, _ = self._server.accept()
        buffer = b""
        with connection:
            connection.settimeout(0.05)
            while not self.hang_up.is_set():
                try:
                    chunk = connection.recv(1024)
                except TimeoutError:
                    continue
                if not chunk:
                    return
                buffer += chunk
                while b"\n" in buffer:
                    line, _, buffer = buffer.partition(b"\n")
                    words = line.decode().split()
                    if self.silent:
                        continue
                    time.sleep(self.delay)
                    if words[0] == "SET":
                        self.sets.append(line.decode())
                        pairs = dict(zip(words[1::2], words[2::2], strict=True))
                        if "POS" in pairs:
                            self.values["POS"] = int(pairs["POS"])
                        connection.sendall(b"ack\n")
                    else:
                        connection.sendall(f"{words[1]} {self.values[words[1]]}\n".encode())


@contextmanager
def connected(timeout: float = 2.0) -> Iterator[tuple[URCap, RobotiqGripper]]:
    """A URCap socket and a gripper connected to it, closed after."""
    urcap = URCap()
    gripper = RobotiqGripper("127.0.0.1", port=urcap.port, timeout=timeout)
    try:
        yield urcap, gripper
    finally:
        gripper.close()


def test_a_slow_answer_never_holds_the_loop_and_the_newest_command_is_sent():
    with connected() as (urcap, gripper):
        assert gripper.opening() == pytest.approx(0.085)
        urcap.delay = 0.15  # every answer later than a 10 Hz control period
        calls = []
        for closure in (0.2, 0.6, 1.0):
            started = time.perf_counter()
            gripper.command(closure)
            gripper.opening()
            calls.append(time.perf_counter() - started)
        assert max(calls) < 0.02, f"the loop waited {1000 * max(calls):.0f} ms for the socket"
        deadline = time.monotonic() + 2.0
        while gripper.opening() > 0.001 and time.monotonic() < deadline:
            time.sleep(POLL_PERIOD)
        assert gripper.opening() == pytest.approx(0.0, abs=1e-9), "the newest command wins"
        assert urcap.sets[-1] == "SET POS 255 GTO 1"
        assert len([s for s in urcap.sets if "POS" in s]) <= 3


def test_a_lost_connection_reaches_the_loop_as_one_line():
    with connected() as (urcap, gripper):
        urcap.hang_up.set()
        deadline = time.monotonic() + 2.0
        with pytest.raises(GripperError) as raised:
            while time.monotonic() < deadline:
                gripper.opening()
                time.sleep(POLL_PERIOD)
        message = str(raised.value)
        assert "\n" not in message and "Robotiq gripper at 127.0.0.1" in message
        with pytest.raises(GripperError):  # and keeps being said
            gripper.command(1.0)


def test_a_gripper_that_stops_answering_is_said_within_its_timeout():
    with connected(timeout=0.3) as (urcap, gripper):
        urcap.silent = True
        time.sleep(0.6)
        with pytest.raises(GripperError, match="has not answered|lost the Robotiq"):
            gripper.opening()
