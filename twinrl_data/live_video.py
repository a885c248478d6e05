"""A live episode's camera frames, encoded once: H.264 intra frames in the log, remuxed
into a dataset's videos.

A live episode (:mod:`twinrl_data.streams`) logs every camera frame as one H.264 frame
(``foxglove.CompressedVideo``, Annex B, its parameter sets repeated, so each message
decodes on its own as Foxglove and Rerun expect). Every frame is a keyframe: any one
decodes alone, so the log is read like a log of JPEGs, and export (:mod:`twinrl_data.
live_export`) builds each camera's video of the dataset's rows by copying the frames'
packets into an MP4, repeating a frame where a camera dropped one, with no decoding or
encoding. Encoding once this way costs about half of a JPEG at quality 90 (1.37 against
2.71 ms a 640x480 frame on a 2-core host, ``bench/bench_live_encoding.py``), where the
recorder once encoded every frame twice (JPEG for the log, H.264 for export), and a
frame takes a fifth of the bytes.

The rows: a live episode exports at its cameras' rate, in *rows* one period apart from
the first frame of its first camera (the *reference*); each row takes the reference
camera's newest frame half a period after its time, which is every frame once when the
camera delivers at its rate and a frame repeated where it dropped one (the rows keep the
clock's time).

The encoder is x264's ``ultrafast`` preset with ``zerolatency`` (a frame's packet comes
out as the frame goes in: a crash loses no frame to the encoder) at ``crf`` 23, x264's
default quality, since the log is the record every dataset is made from. lerobot is
told these settings (:func:`twinrl_data.live_export.encoder_config`). AV1, lerobot's
default codec, took more than a core for two 640x480 cameras at 30 fps on a 2-core host.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from fractions import Fraction

import numpy as np
import PIL.Image

from twinrl_data.errors import DataError

VIDEO_CODEC = "h264"
VIDEO_PRESET = "ultrafast"
VIDEO_GOP = 1  # every frame a keyframe: each decodes alone, and any can be repeated
VIDEO_CRF = 23
VIDEO_PIX_FMT = "yuv420p"
VIDEO_OPTIONS = {"g": str(VIDEO_GOP), "crf": str(VIDEO_CRF), "preset": VIDEO_PRESET}
FRAME_FORMAT = "h264"  # ``CompressedVideo.format``
_ANNEX_B = (b"\x00\x00\x00\x01", b"\x00\x00\x01")  # how an H.264 frame's bytes begin


class FrameEncoder:
    """One camera's frames as H.264 intra frames, each a packet of its own."""

    def __init__(self, camera: str) -> None:
        self.camera = camera
        self.frames = 0
        self._context = None
        self._shape: tuple[int, ...] | None = None

    def encode(self, image: np.ndarray) -> bytes:
        """One RGB frame (H x W x 3, uint8, even sides) as its H.264 packet."""
        import av
        import cv2

        if self._context is None:
            height, width = image.shape[:2]
            if height % 2 or width % 2 or image.ndim != 3 or image.shape[2] != 3:
                raise DataError(
                    f"camera {self.camera}'s frames are {image.shape}: H.264 needs an RGB "
                    "image of even width and height; set the camera to such a size"
                )
            context = av.CodecContext.create("libx264", "w")
            context.width, context.height, context.pix_fmt = width, height, VIDEO_PIX_FMT
            context.time_base = Fraction(1, 1000)
            context.options = {
                **VIDEO_OPTIONS,
                "tune": "zerolatency",
                "threads": "1",  # one core: the recorder's budget
                "x264-params": "log=-1:repeat-headers=1",
            }
            self._context, self._shape = context, image.shape
        elif image.shape != self._shape:
            raise DataError(
                f"camera {self.camera}'s frame {self.frames} is {image.shape}, its first was "
                f"{self._shape}: a camera keeps one size through an episode"
            )
        yuv = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2YUV_I420)
        frame = av.VideoFrame.from_ndarray(yuv, format=VIDEO_PIX_FMT)
        frame.pts = self.frames
        packets = self._context.encode(frame)
        if len(packets) != 1:
            raise DataError(f"camera {self.camera}'s frame {self.frames} was not encoded alone")
        self.frames += 1
        return bytes(packets[0])


def is_h264(data: bytes) -> bool:
    """Whether a logged frame is an H.264 frame (else a JPEG or PNG image)."""
    return data.startswith(_ANNEX_B)


def decode_frame(data: bytes) -> np.ndarray:
    """A logged camera frame (an H.264 intra frame, a JPEG or a PNG) as RGB (H x W x 3)."""
    if is_h264(data):
        import av

        context = av.CodecContext.create(VIDEO_CODEC, "r")
        frames = context.decode(av.Packet(data)) + context.decode(None)
        if not frames:
            raise DataError("a logged H.264 camera frame does not decode on its own")
        return frames[0].to_ndarray(format="rgb24")
    return np.asarray(PIL.Image.open(io.BytesIO(data)).convert("RGB"))


def remux(frames: Sequence[bytes], fps: int) -> bytes:
    """An MP4 of H.264 intra frames, frame ``i`` at ``i / fps``: their packets copied,
    none decoded or encoded (a frame may repeat)."""
    import av

    width, height = decode_frame(frames[0]).shape[1::-1]
    buffer = io.BytesIO()
    with av.open(buffer, "w", format="mp4") as container:
        stream = container.add_stream(VIDEO_CODEC, rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, VIDEO_PIX_FMT
        stream.time_base = Fraction(1, fps)
        for index, data in enumerate(frames):
            packet = av.Packet(data)
            packet.pts = packet.dts = index
            packet.time_base, packet.stream, packet.is_keyframe = Fraction(1, fps), stream, True
            container.mux(packet)
    return buffer.getvalue()


def row_count(first: float, last: float, fps: float) -> int:
    """The rows of a live episode whose reference camera's frames were captured from
    ``first`` to ``last`` (s): one a period from the first, as many as the frames when
    the camera delivered at ``fps``."""
    return math.floor((last - first) * fps + 0.25) + 1


def row_time(first: float, row: int, fps: float) -> float:
    """When a row takes the reference camera's newest frame (s, the frames' clock): half
    a period after the frame the camera delivers then, whatever its jitter."""
    return first + (row + 0.5) / fps
