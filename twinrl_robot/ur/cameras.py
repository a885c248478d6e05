"""Cameras of a real cell, behind one small protocol.

Each camera is read in its own thread with latest-frame semantics: the thread keeps
only the newest frame and its capture time (host monotonic clock), so a control step
never waits for a camera and never reads a backlog. :class:`CameraRig` matches frames
to control steps and counts what a recording must not hide: frames the camera failed
to deliver (``dropped``: read failures and gaps longer than 1.5 frame periods) and
control steps that got the frame an earlier step already had or one older than two
frame periods (``stale``). Those counts go into the episode's metadata.

* :class:`OpenCVCamera`: a USB/V4L2 device index, a video file, or any URL OpenCV opens
  (the emulator serves its rendered cameras as MJPEG over HTTP, read by this class).
* :class:`RealSenseCamera`: an Intel RealSense by serial number (``pyrealsense2``, the
  ``realsense`` extra), stamped with the device's own capture time.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from twinrl_robot.errors import RobotError

OPEN_TIMEOUT = 10.0  # s for the first frame
STALE_PERIODS = 2.0  # a frame older than this many frame periods is stale


class CameraError(RobotError):
    """A camera cannot be opened or stopped delivering frames."""


@dataclass(frozen=True)
class Frame:
    image: np.ndarray  # H x W x 3 uint8 RGB, at the contract's size
    stamp: float  # capture time, host monotonic clock (s)
    index: int  # counts frames delivered by this camera


@dataclass
class CameraStats:
    """What a camera delivered, and what control steps made of it."""

    frames: int = 0
    dropped: int = 0
    stale: int = 0
    first_stamp: float | None = None
    last_stamp: float | None = None
    latencies: list[float] = field(default_factory=list)  # s from capture to use

    @property
    def fps(self) -> float:
        if self.first_stamp is None or self.last_stamp is None or self.frames < 2:
            return 0.0
        return (self.frames - 1) / max(self.last_stamp - self.first_stamp, 1e-9)


@runtime_checkable
class Camera(Protocol):
    name: str
    fps: float
    stats: CameraStats
    tap: Callable[[Frame], None] | None

    def latest(self) -> Frame | None: ...

    def close(self) -> None: ...


class ThreadedCamera(ABC):
    """A camera read by its own thread; subclasses define :meth:`_grab`."""

    def __init__(self, name: str, width: int, height: int, fps: float) -> None:
        self.name, self.size, self.fps = name, (width, height), fps
        self.stats = CameraStats()
        self._latest: Frame | None = None
        self._lock = threading.Lock()
        self._running = True
        self._failure: str | None = None
        self.tap: Callable[[Frame], None] | None = None  # given every frame (a recorder)
        self._thread = threading.Thread(target=self._run, name=f"camera-{name}", daemon=True)

    def _start(self) -> None:
        self._thread.start()
        deadline = time.monotonic() + OPEN_TIMEOUT
        while self._latest is None:
            if self._failure or time.monotonic() > deadline:
                self.close()
                raise CameraError(
                    f"camera '{self.name}' delivered no frame in {OPEN_TIMEOUT:g} s"
                    f"{f' ({self._failure})' if self._failure else ''}; check its source in "
                    "the cell file and that no other program holds it"
                )
            time.sleep(0.01)

    @abstractmethod
    def _grab(self) -> tuple[np.ndarray, float] | None:
        """The next RGB frame and its capture time, or ``None`` on a failed read."""

    def _run(self) -> None:
        failures = 0
        while self._running:
            try:
                grabbed = self._grab()
            except Exception as err:  # a device error ends the stream; latest() reports it
                self._failure = str(err)
                return
            if grabbed is None:
                failures += 1
                self.stats.dropped += 1
                if failures > 50:
                    self._failure = "50 reads in a row failed"
                    return
                time.sleep(0.5 / self.fps)
                continue
            failures = 0
            image, stamp = grabbed
            if image.shape[1::-1] != self.size:
                image = cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)
            with self._lock:
                previous = self._latest
                if previous is not None:
                    missed = round((stamp - previous.stamp) * self.fps) - 1
                    self.stats.dropped += max(0, missed)
                self.stats.frames += 1
                self.stats.first_stamp = self.stats.first_stamp or stamp
                self.stats.last_stamp = stamp
                self._latest = Frame(image, stamp, self.stats.frames)
            tap = self.tap
            if tap is not None:
                tap(self._latest)

    def latest(self) -> Frame | None:
        if self._failure and self._running:
            raise CameraError(f"camera '{self.name}' stopped: {self._failure}")
        with self._lock:
            return self._latest

    def close(self) -> None:
        self._running = False
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)


class OpenCVCamera(ThreadedCamera):
    """A camera OpenCV opens: a device index (``"0"``), a file, or a URL."""

    def __init__(self, name: str, source: str, width: int, height: int, fps: float) -> None:
        super().__init__(name, width, height, fps)
        target: int | str = int(source) if source.isdigit() else source
        self._capture = cv2.VideoCapture(target)
        if not self._capture.isOpened():
            raise CameraError(
                f"camera '{name}' cannot be opened from source {source!r}; check the device "
                "index, path or URL in the cell file (v4l2-ctl lists the video devices)"
            )
        if isinstance(target, int):
            self._capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            self._capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            self._capture.set(cv2.CAP_PROP_FPS, fps)
            self._capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        self._start()

    def _grab(self) -> tuple[np.ndarray, float] | None:
        ok, bgr = self._capture.read()
        stamp = time.monotonic()
        if not ok or bgr is None:
            return None
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), stamp

    def close(self) -> None:
        super().close()
        self._capture.release()


class RealSenseCamera(ThreadedCamera):
    """An Intel RealSense colour stream by serial number (needs ``pyrealsense2``)."""

    def __init__(self, name: str, serial: str, width: int, height: int, fps: float) -> None:
        super().__init__(name, width, height, fps)
        try:
            import pyrealsense2 as rs
        except ImportError:
            raise CameraError(
                f"camera '{name}' is a RealSense, which needs pyrealsense2: "
                "pip install 'twinrl[realsense]'"
            ) from None
        self._rs = rs
        self._pipeline = rs.pipeline()
        config = rs.config()
        config.enable_device(serial)
        config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, int(fps))
        try:
            self._pipeline.start(config)
        except RuntimeError as err:
            raise CameraError(f"RealSense '{name}' (serial {serial}) cannot start: {err}") from None
        self._offset: float | None = None
        self._start()

    def _grab(self) -> tuple[np.ndarray, float] | None:
        frames = self._pipeline.wait_for_frames(timeout_ms=int(2000 / self.fps) + 100)
        color = frames.get_color_frame()
        if not color:
            return None
        device_stamp = color.get_timestamp() / 1000.0  # ms, the device's clock
        if self._offset is None:  # map the device clock onto the host's once
            self._offset = time.monotonic() - device_stamp
        return np.asanyarray(color.get_data()).copy(), device_stamp + self._offset

    def close(self) -> None:
        super().close()
        self._pipeline.stop()


class CameraRig:
    """The cell's cameras, matched to control steps (see the module docstring)."""

    def __init__(self, cameras: list[Camera]) -> None:
        self.cameras = cameras
        self._used: dict[str, int] = {}
        # When the newest frame the last ``images`` gave was captured (host clock).
        self.captured_at: float | None = None

    def images(self) -> dict[str, np.ndarray]:
        """Each camera's newest frame for this control step, keyed like the contract."""
        now = time.monotonic()
        images, stamps = {}, []
        for camera in self.cameras:
            frame = camera.latest()
            if frame is None:
                raise CameraError(f"camera '{camera.name}' has no frame yet")
            age = now - frame.stamp
            if self._used.get(camera.name) == frame.index or age > STALE_PERIODS / camera.fps:
                camera.stats.stale += 1
            self._used[camera.name] = frame.index
            camera.stats.latencies.append(age)
            images[f"observation.images.{camera.name}"] = frame.image
            stamps.append(frame.stamp)
        self.captured_at = max(stamps, default=None)
        return images

    def counts(self) -> dict[str, dict[str, int]]:
        """Per camera: frames delivered, dropped and stale (for episode metadata)."""
        return {
            c.name: {"frames": c.stats.frames, "dropped": c.stats.dropped, "stale": c.stats.stale}
            for c in self.cameras
        }

    def close(self) -> None:
        for camera in self.cameras:
            camera.close()
