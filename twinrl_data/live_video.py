"""A live episode's cameras encoded as video while it is recorded, ready for a dataset.

A live episode (:mod:`twinrl_data.streams`) exports to LeRobot at its cameras' rate: one
dataset frame per frame of its first camera (the *reference*), at that frame's capture
time. :class:`RowVideos` encodes every camera's video of those frames as they come, in
the episode's writer thread: the reference camera's every frame, and for each other
camera the newest frame it had captured by each reference frame's time (its first
frame before it had any). Export then only copies the videos
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


class RowVideos:
    """Every camera's video at the reference camera's frames (see the module docstring).

    Frames come as the cameras deliver them; each camera's own in capture order, the
    cameras' interleaving by up to one frame out of order."""

    def __init__(self, cameras: Sequence[str], fps: int) -> None:
        self.reference, *others = cameras
        self.videos = {camera: CameraVideo(fps) for camera in cameras}
        self._waiting: dict[str, list[float]] = {camera: [] for camera in others}  # row times
        self._recent: dict[str, list[tuple[float, np.ndarray]]] = {c: [] for c in others}

    def frame(self, camera: str, image: np.ndarray, captured: float) -> None:
        """A camera's frame (RGB) captured at ``captured`` (any clock, the same for all)."""
        if camera == self.reference:
            self.videos[camera].encode(image)
            for times in self._waiting.values():
                times.append(captured)
            return
        recent = self._recent[camera]
        recent.append((captured, image))
        del recent[:-2]  # the newest two: a row may come after a frame captured later
        self._resolve(camera, before=captured)

    def _resolve(self, camera: str, before: float) -> None:
        """Encode this camera's frame for every waiting row captured before ``before``."""
        recent, times = self._recent[camera], self._waiting[camera]
        while times and times[0] < before and recent:
            row = times.pop(0)
            earlier = [image for captured, image in recent if captured <= row]
            self.videos[camera].encode(earlier[-1] if earlier else recent[0][1])

    def close(self) -> dict[str, bytes]:
        """Each camera's MP4 with one frame per reference frame (none for a camera that
        delivered no frame)."""
        for camera in self._waiting:
            self._resolve(camera, before=math.inf)
        return {
            camera: data
            for camera, video in self.videos.items()
            if (data := video.close()) and video.frames == self.videos[self.reference].frames
        }
