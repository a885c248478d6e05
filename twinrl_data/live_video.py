"""A live episode's cameras encoded as video while it is recorded, ready for a dataset.

A live episode (:mod:`twinrl_data.streams`) exports to LeRobot at its cameras' rate, in
*rows* one period apart from the first frame of its first camera (the *reference*):
each row takes the reference camera's newest frame half a period after its time, which
is every frame once when the camera delivers at its rate, a frame repeated where it
dropped one (the rows keep the clock's time), and for each other camera the newest
frame it had captured by that reference frame's capture (its first frame before it had
any). :class:`RowVideos` encodes every camera's video of the rows as the frames come,
in the episode's writer thread. Export then only copies the videos
(:mod:`twinrl_data.live_export`), where encoding them from the episode's JPEG frames
costs more than lerobot's own recording loop.

The videos are H.264 with the options of lerobot's ``RGBEncoderConfig(vcodec="h264",
preset="ultrafast")`` (a keyframe every 2 frames, as lerobot's default, so training
decodes any frame quickly): AV1, lerobot's default codec, took more than a core for
two 640x480 cameras at 30 fps on a 2-core host.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from fractions import Fraction

import av
import numpy as np

VIDEO_CODEC = "h264"
VIDEO_PRESET = "ultrafast"
VIDEO_GOP = 2
VIDEO_CRF = 30
VIDEO_PIX_FMT = "yuv420p"
VIDEO_OPTIONS = {"g": str(VIDEO_GOP), "crf": str(VIDEO_CRF), "preset": VIDEO_PRESET}


class CameraVideo:
    """One camera's frames encoded into an MP4 held in memory (frame ``i`` at ``i / fps``)."""

    def __init__(self, fps: int) -> None:
        self.fps = fps
        self.frames = 0
        self._buffer = io.BytesIO()
        self._container: av.container.OutputContainer | None = None
        self._stream: av.video.stream.VideoStream | None = None

    def encode(self, image: np.ndarray) -> None:
        """Append one RGB frame (H x W x 3, uint8)."""
        if self._container is None:
            self._container = av.open(self._buffer, "w", format="mp4")
            # one core (the recorder's budget), and no statistics printed when it closes
            options = {**VIDEO_OPTIONS, "threads": "1", "x264-params": "log=-1"}
            self._stream = self._container.add_stream(VIDEO_CODEC, self.fps, options=options)
            self._stream.pix_fmt = VIDEO_PIX_FMT
            self._stream.height, self._stream.width = image.shape[:2]
            self._stream.time_base = Fraction(1, self.fps)
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        frame.pts, frame.time_base = self.frames, Fraction(1, self.fps)
        self._container.mux(self._stream.encode(frame))
        self.frames += 1

    def close(self) -> bytes:
        """The finished MP4 (empty when no frame came)."""
        if self._container is None:
            return b""
        self._container.mux(self._stream.encode())
        self._container.close()
        return self._buffer.getvalue()


def row_count(first: float, last: float, fps: float) -> int:
    """The rows of a live episode whose reference camera's frames were captured from
    ``first`` to ``last`` (s): one a period from the first, as many as the frames when
    the camera delivered at ``fps``."""
    return math.floor((last - first) * fps + 0.25) + 1


def row_time(first: float, row: int, fps: float) -> float:
    """When a row takes the reference camera's newest frame (s, the frames' clock): half
    a period after the frame the camera delivers then, whatever its jitter."""
    return first + (row + 0.5) / fps


class RowVideos:
    """Every camera's video of a live episode's rows (see the module docstring).

    Frames come as the cameras deliver them, each camera's own in capture order."""

    def __init__(self, cameras: Sequence[str], fps: int) -> None:
        self.reference, *others = cameras
        self.fps = fps
        self.videos = {camera: CameraVideo(fps) for camera in cameras}
        self.rows = 0
        self._last_row = -math.inf  # the newest row's time
        self._first: float | None = None  # the reference camera's first capture
        self._newest: tuple[float, np.ndarray] | None = None  # and its newest frame
        self._waiting: dict[str, list[float]] = {camera: [] for camera in others}  # row times
        self._recent: dict[str, list[tuple[float, np.ndarray]]] = {c: [] for c in others}

    def frame(self, camera: str, image: np.ndarray, captured: float) -> None:
        """A camera's frame (RGB) captured at ``captured`` (any clock, the same for all)."""
        if camera == self.reference:
            if self._first is None:
                self._first = captured
            while row_time(self._first, self.rows, self.fps) < captured:
                self._add_row()  # the rows before this frame: the newest before it
            self._newest = (captured, image)
            return
        self._recent[camera].append((captured, image))
        self._resolve(camera, before=captured)

    def _add_row(self) -> None:
        captured, image = self._newest
        self.videos[self.reference].encode(image)
        for times in self._waiting.values():
            times.append(captured)
        self._last_row = captured
        self.rows += 1

    def _resolve(self, camera: str, before: float) -> None:
        """Encode this camera's frame for every waiting row captured before ``before``."""
        recent, times = self._recent[camera], self._waiting[camera]
        while times and times[0] < before and recent:
            row = times.pop(0)
            earlier = [image for captured, image in recent if captured <= row]
            self.videos[camera].encode(earlier[-1] if earlier else recent[0][1])
        # Kept: the newest frame by the next row's time and those after it, a second's
        # worth at most (while the reference camera delivers nothing, no row comes).
        horizon = times[0] if times else self._last_row
        older = [i for i, (captured, _) in enumerate(recent) if captured <= horizon]
        del recent[: max(older[-1] if older else 0, len(recent) - self.fps)]

    def close(self) -> dict[str, bytes]:
        """Each camera's MP4 with one frame per row (none for a camera that delivered no
        frame)."""
        if self._newest is not None:
            while self.rows < row_count(self._first, self._newest[0], self.fps):
                self._add_row()
        for camera in self._waiting:
            self._resolve(camera, before=math.inf)
        return {
            camera: data
            for camera, video in self.videos.items()
            if (data := video.close()) and video.frames == self.rows
        }
