"""A UR cell's sensors at their own rates, for a live episode (:mod:`twinrl_data.streams`).

- **Cameras**: every frame each camera's thread delivers, handed over as it comes (the
  recorder encodes it in its own thread).
- **The controller's state** at its servo rate (500 Hz on an e-Series): ur_rtde's
  receive interface, in the controller link's process, writes every package it
  receives to a CSV file of its own (``startFileRecording``, in its C++ receive thread:
  no package is skipped however busy the host's interpreter is), and a thread here
  reads the new rows every :data:`READ_PERIOD` and hands them over, each stamped with
  the controller's time mapped onto the host's clock. The offset is the smallest
  host-minus-controller time seen over the last :data:`DRIFT_WINDOW` of observations:
  a package never looks older than it is by more than the clocks drift apart within
  that window (1.5 ms at 50 ppm), and that drift (a controller's clock tens of ppm off
  the host's: a tenth of a second an hour) is followed rather than piling up over a
  long session. An episode's packages keep the offset of its first rows, in order; each
  step is logged at its own package's time, or at its frames' capture if later. ur_rtde
  writes a package's row again when no new one came in between; a row whose timestamp
  is not newer than the last is skipped.
- **The observation's state at the same rate** (stream ``observation.state``, the
  contract's entries): each package's joints and speeds, the TCP pose from the twin's
  kinematics of those joints, and the gripper's opening as the last observation read it
  (the gripper reports at the control rate). Export to LeRobot at the cameras' rate
  reads the state from it (:mod:`twinrl_data.live_export`).
"""

from __future__ import annotations

import shutil
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data.schema import STATE
from twinrl_robot.ur.cameras import CameraRig, Frame

READ_PERIOD = 0.2  # s between reads of the controller's new rows
# s of observations whose smallest host-minus-controller time is the clock offset: long
# enough to hold a quick read on a loaded host (hundreds of reads), short enough that a
# drift of 100 ppm moves the offset by 3 ms at most within it
DRIFT_WINDOW = 30.0
VARIABLES = ("timestamp", "actual_q", "actual_qd", "target_q", "target_moment", "actual_TCP_force")
JOINTS = 6


def controller_names() -> list[str]:
    """Names of a controller sample's entries (timestamp aside)."""
    names = [f"q.{i}" for i in range(JOINTS)] + [f"qd.{i}" for i in range(JOINTS)]
    names += [f"target_q.{i}" for i in range(JOINTS)] + [f"tau.{i}" for i in range(JOINTS)]
    return names + ["force.x", "force.y", "force.z", "torque.x", "torque.y", "torque.z"]


StateOf = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""The observation's state (n x entries) of ``n`` packages' joints and speeds (n x 6 each)."""


class SensorStreams:
    """The cameras of ``rig`` and the controller's state through ``receive`` (ur_rtde's
    receive interface, or the link's proxy of it), handed to a live episode; with
    ``state_of`` (and its entries' ``state_names``) the observation's state as well."""

    def __init__(
        self,
        rig: CameraRig,
        receive: Any,
        servo_hz: float,
        state_of: StateOf | None = None,
        state_names: list[str] | None = None,
    ) -> None:
        self.rig, self.receive, self.servo_hz = rig, receive, servo_hz
        self.state_of = state_of
        self.samples = {"controller": controller_names()}
        if state_of is not None:
            self.samples[STATE] = list(state_names or [])
        self.offset: float | None = None  # s, host monotonic minus controller time
        self.received = 0  # controller packages read this episode
        self.handed: dict[str, int] = {}  # frames handed over this episode, per camera
        self.cpu = 0.0  # s of CPU the reading thread used this episode
        self._live: Any = None
        self._folder: Path | None = None
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None
        self._episode_offset = 0.0  # s, the offset this episode's packages are mapped with
        # (host time, offset) of the observations that may still be the window's lowest
        self._lows: deque[tuple[float, float]] = deque()

    @property
    def cameras(self) -> dict[str, float]:
        """The streamed cameras and their frame rates."""
        return {camera.name: camera.fps for camera in self.rig.cameras}

    def saw(self, controller_time: float, host_time: float) -> None:
        """An observation read the controller's ``controller_time`` by ``host_time``: the
        offset becomes the lowest of the last :data:`DRIFT_WINDOW` s of observations."""
        offset = host_time - controller_time
        lows = self._lows
        while lows and lows[-1][1] >= offset:  # never the lowest while this one is seen
            lows.pop()
        lows.append((host_time, offset))
        while lows[0][0] < host_time - DRIFT_WINDOW:
            lows.popleft()
        self.offset = lows[0][1]

    def start(self, live: Any) -> None:
        """Hand every camera frame and controller package to ``live`` from now on."""
        self._live, self.received = live, 0
        self.handed = dict.fromkeys(self.cameras, 0)
        for camera in self.rig.cameras:
            camera.tap = lambda frame, name=camera.name: self._hand_frame(name, frame)
        self._folder = Path(tempfile.mkdtemp(prefix="twinrl-controller-"))
        path = self._folder / "controller.csv"
        self.receive.startFileRecording(str(path), list(VARIABLES))
        self._stop.clear()
        self._reader = threading.Thread(
            target=self._read, args=(path,), name="controller-samples", daemon=True
        )
        self._reader.start()

    def _hand_frame(self, camera: str, frame: Frame) -> None:
        self._live.frame(camera, frame.image, frame.stamp, frame.index)
        self.handed[camera] += 1

    def stop(self) -> None:
        """Stop handing over (the rows written so far are read first)."""
        for camera in self.rig.cameras:
            camera.tap = None
        if self._reader is None:
            return
        self.receive.stopFileRecording()
        self._stop.set()
        self._reader.join()
        self._reader = None
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)

    def _read(self, path: Path) -> None:
        while not path.exists():  # ur_rtde creates it with the first package
            if self._stop.wait(READ_PERIOD / 4):
                return
        rest, last = b"", -np.inf
        with open(path, "rb") as handle:
            while True:
                stopping = self._stop.wait(READ_PERIOD)
                if self.offset is not None:
                    rest, last = self._hand_over(rest + handle.read(), last)
                if stopping:
                    self.cpu = time.thread_time()
                    return

    def _hand_over(self, data: bytes, last: float) -> tuple[bytes, float]:
        """Hand the complete rows of ``data`` newer than ``last`` over; (the incomplete
        rest, the newest timestamp)."""
        complete, _, rest = data.rpartition(b"\n")
        lines = [line for line in complete.split(b"\n") if line[:1].isdigit()]  # no header
        if not lines:
            return rest, last
        rows = np.loadtxt(lines, delimiter=",", ndmin=2)
        rows = rows[rows[:, 0] > np.maximum.accumulate(np.r_[last, rows[:-1, 0]])]
        if len(rows):
            clock = rows[:, 0]
            values = rows[:, 1:].astype(np.float32)
            # A lower offset found since the episode's first rows would map these before
            # rows already handed over, out of order in the log: it keeps the first's.
            if not np.isfinite(last):
                self._episode_offset = self.offset
            received = clock + self._episode_offset
            self._live.samples("controller", received, values, clock)
            if self.state_of is not None:
                joints, speeds = values[:, :JOINTS], values[:, JOINTS : 2 * JOINTS]
                self._live.samples(STATE, received, self.state_of(joints, speeds), clock)
            self.received += len(rows)
            last = float(clock[-1])
        return rest, last
