"""Using an emulator from the outside: start one in its own process, and talk to its
harness channel (what a person at the cell does, what only a simulation knows).

The emulator runs in a process of its own (``twinrl robot emulate``) because ur_rtde's
calls hold the Python interpreter while they wait for the controller: an emulator in
the same process could never answer them.

:class:`EmulatedTruth` lends the emulated plant's ground truth (task success, object
poses) to a driver as its ``privileged`` channel. It exists only for an emulated cell:
a scripted expert that reads object poses, or evaluation by the task's own success
test, works here and not on a real cell, where a person or a reward classifier judges.
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any

import numpy as np

from twinrl_robot.errors import RobotError
from twinrl_robot.ur.emulator.emulator import Ports
from twinrl_sim.tasks import Progress, TaskConfig

READY_PREFIX = "emulating"
START_TIMEOUT = 90.0  # s for the emulator process to serve (it compiles the plant)
ERROR_TAIL = 20  # lines of the emulator's errors shown when the block it serves fails
PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent ends
# Looked up here, not in the child between fork and exec, where little is safe to run.
_PRCTL = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None


class HarnessClient:
    """The emulator's harness channel: one JSON request per line, one answer each."""

    def __init__(self, host: str, port: int = Ports.harness, timeout: float = 10.0) -> None:
        self.address = (host, port)
        self._socket = socket.create_connection(self.address, timeout=timeout)
        self._file = self._socket.makefile("rwb")
        self._lock = threading.Lock()

    def request(self, do: str, **arguments: Any) -> dict[str, Any]:
        with self._lock:
            self._file.write(json.dumps({"do": do, **arguments}).encode() + b"\n")
            self._file.flush()
            line = self._file.readline()
        if not line:
            raise RobotError(f"the emulator at {self.address[0]} closed its harness channel")
        answer = json.loads(line)
        if not answer.get("ok"):
            raise RobotError(f"the emulator refused '{do}': {answer.get('error')}")
        return answer

    def arrange(self, config: TaskConfig) -> None:
        """Set the configuration's objects up (the arm stays where it is)."""
        self.request("arrange", config=config.to_dict())

    def fault(self, kind: str) -> None:
        """``protective_stop``, ``emergency_stop``, ``release_emergency_stop``,
        ``local_mode``, ``remote_mode``, ``drop_connection``, or ``speed_slider_0``,
        ``speed_slider_20``, ``speed_slider_100`` (the pendant's speed slider)."""
        self.request(kind)

    def reading(self) -> dict[str, Any]:
        """The arm's joints, speeds, controller time and safety mode, straight from the plant."""
        return self.request("reading")

    def close(self) -> None:
        self._file.close()
        self._socket.close()


class EmulatedTruth:
    """The ground truth of an emulated cell, as a driver's ``privileged`` channel."""

    def __init__(self, harness: HarnessClient, environment_names: list[str]) -> None:
        self.harness = harness
        self._names = environment_names

    @property
    def progress(self) -> Progress:
        truth = self.harness.request("truth")
        return Progress(success=truth["success"], terms=truth["terms"])

    @property
    def success(self) -> bool:
        return bool(self.harness.request("truth")["success"])

    @property
    def environment_names(self) -> list[str]:
        return self._names

    def environment_state(self) -> np.ndarray:
        return np.array(self.harness.request("truth")["environment_state"], np.float32)

    def close(self) -> None:
        self.harness.close()


def _ends_with_its_parent() -> None:
    """In the emulator's process, before it runs: on Linux, the kernel ends it when the
    process that started it ends, however that ends (a killed benchmark or test would
    otherwise leave it holding the cell's ports). Strictly, when the starting thread
    ends, which a ``with`` block outlives."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, int(signal.SIGTERM))


class EmulatorProcess:
    """``twinrl robot emulate CELL`` in a process of its own, for as long as the context
    and no longer than the process that started it.

    Args:
        cell_file: the cell file; the emulator serves on its ``arm.host`` (a loopback
            address).
        task: the task whose plant it runs (default: the cell's twin).
        effects: the plant's hidden effects file (default: the built-in plant).
    """

    def __init__(
        self, cell_file: str | Path, *, task: str | None = None, effects: str | Path | None = None
    ) -> None:
        self.command = [sys.executable, "-m", "twinrl_learn", "robot", "emulate", str(cell_file)]
        if task:
            self.command += ["--task", task]
        if effects is not None:
            self.command += ["--effects", str(effects)]
        self.process: subprocess.Popen[str] | None = None
        self.log: IO[str] | None = None
        self.banner = ""

    def __enter__(self) -> EmulatorProcess:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        # Its errors go to a file: a pipe nobody reads would fill and stall the emulator.
        self.log = tempfile.NamedTemporaryFile("w+", prefix="twinrl-emulator-", suffix=".log")
        self.process = subprocess.Popen(
            self.command,
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
            env=env,
            preexec_fn=_ends_with_its_parent,
        )
        deadline = time.monotonic() + START_TIMEOUT
        assert self.process.stdout is not None
        while time.monotonic() < deadline:
            line = self.process.stdout.readline()
            if line.startswith(READY_PREFIX):
                self.banner = line.strip()
                return self
            if not line and self.process.poll() is not None:
                break
        self.__exit__()
        error = self.errors().strip()
        last = error.splitlines()[-1] if error else "no output"
        raise RobotError(f"the emulator did not start: {last}")

    def __exit__(self, *exc: object) -> None:
        if exc and exc[0] is not None:  # what went wrong, as the controller saw it
            tail = self.errors().strip().splitlines()[-ERROR_TAIL:]
            print("\n".join(["the emulator's last words:", *tail]), file=sys.stderr)
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def errors(self) -> str:
        """What the emulator wrote to its error stream so far."""
        return Path(self.log.name).read_text() if self.log is not None else ""
