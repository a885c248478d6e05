"""Live episodes: a real cell's sensors recorded at their own rates, on one clock.

A live episode holds the control steps of the contract (:mod:`twinrl_data.schema`) plus
what the sensors delivered between them, each at its rate: **every camera frame** (a
real cell's 30 fps, on ``/camera/<name>``, stamped with its capture time) and **sample
streams** such as the controller's state at its servo rate (500 Hz on an e-Series, on
``/samples/<name>``, one ``twinrl.FloatVector`` per sample). Every message's log time
is the host's monotonic clock, counted from the episode's start and added to its
``created_at``: a step at the moment of its observation, a frame at its capture, a
controller sample at its controller time mapped onto the host's clock. A metadata
record ``twinrl.streams`` names the streamed cameras and each sample stream's entries.
Read as an episode, a streamed camera gives each step the newest frame captured by
the step's time, as the step's observation saw it; :func:`read_samples` reads the
sample streams.

:class:`LiveEpisode` writes one from a background thread: the control loop, the
cameras' threads and the sample readers only hand their data over (a queue), and the
thread encodes each frame once, as an H.264 intra frame (``foxglove.CompressedVideo``,
:mod:`twinrl_data.live_video`: what export copies into the dataset's videos as it is),
and writes and closes a chunk every ``flush_seconds`` of the host's clock (half a second
by default: with the controller's samples read every 0.2 s, a crash loses under a second
of any stream, plus what is queued). A crashed episode, recovered, exports as one that
ended.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo

from twinrl_data import schema as contract
from twinrl_data.errors import DataError
from twinrl_data.live_video import FRAME_FORMAT, FrameEncoder
from twinrl_data.mcap_log import (
    CAMERA_PREFIX,
    META_START,
    META_STREAMS,
    EpisodeWriter,
    _iso_to_ns,
    intact_records,
    read_episode,
)
from twinrl_data.messages import FloatVector
from twinrl_data.schema import Samples

SAMPLES_PREFIX = "/samples/"


class LiveEpisode:
    """Writes an episode's steps, camera frames and sample streams from one background
    thread (see the module docstring).

    ``cameras`` maps the streamed cameras to their frame rates; ``samples`` each sample
    stream to the names of its entries. Times are host monotonic seconds
    (``time.monotonic()``); the episode's clock starts at ``started``.
    """

    def __init__(
        self,
        writer: EpisodeWriter,
        *,
        cameras: Mapping[str, float],
        samples: Mapping[str, Sequence[str]],
        started: float,
        flush_seconds: float = 0.5,
    ) -> None:
        self.writer, self.started, self.flush_seconds = writer, started, flush_seconds
        self.cameras = dict(cameras)
        self.counts = {name: 0 for name in [*cameras, *samples]}  # frames, samples written
        self.backlog = 0  # the most items the thread had waiting
        self.cpu = 0.0  # s of CPU the thread used (once closed)
        self._start_ns = _iso_to_ns(writer.meta.created_at)
        writer.add_metadata(
            META_STREAMS,
            {"cameras": self.cameras, "samples": {k: list(v) for k, v in samples.items()}},
        )
        self._encoders = {camera: FrameEncoder(camera) for camera in cameras}
        self._queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="live-episode", daemon=True)
        self._thread.start()

    # -------------------------------------------------------- from any thread
    def step(self, step: Mapping[str, Any], observed: float) -> None:
        """A control step whose observation was taken at ``observed``; the images of
        streamed cameras are left to their streams."""
        contract.validate_step(step)
        streamed = {contract.image_field(camera) for camera in self.cameras}
        self._put(("step", {k: v for k, v in step.items() if k not in streamed}, observed))

    def frame(self, camera: str, image: np.ndarray, captured: float, index: int) -> None:
        """A camera's frame (RGB), captured at ``captured``, its ``index`` the camera's count."""
        self._put(("frame", camera, image, captured, index))

    def samples(
        self, stream: str, received: np.ndarray, rows: np.ndarray, clock: np.ndarray
    ) -> None:
        """Samples of ``stream`` (one row each) at host times ``received``, with their
        source's own times ``clock``."""
        self._put(("samples", stream, received, rows, clock))

    def _put(self, item: tuple[Any, ...]) -> None:
        if self._error is not None:
            raise DataError(f"the episode's writer stopped: {self._error}")
        self._queue.put(item)

    # ---------------------------------------------------------------- closing
    def close(self) -> None:
        """Write what is queued and stop the thread (the writer stays open)."""
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            raise DataError(f"the episode's writer stopped: {self._error}")

    # ------------------------------------------------------------ the thread
    def _ns(self, seconds: float) -> int:
        return self._start_ns + max(0, round((seconds - self.started) * 1e9))

    def _run(self) -> None:
        flushed = time.monotonic()
        try:
            while True:
                try:
                    item = self._queue.get(timeout=self.flush_seconds / 4)
                except queue.Empty:
                    item = ()
                if item is None:
                    return
                if item:
                    self.backlog = max(self.backlog, self._queue.qsize())
                    self._write(item)
                if time.monotonic() - flushed >= self.flush_seconds:
                    self.writer.flush()
                    flushed = time.monotonic()
        except BaseException as err:  # reported to the next caller; the loop goes on
            self._error = err
        finally:
            self.cpu = time.thread_time()

    def _write(self, item: tuple[Any, ...]) -> None:
        kind = item[0]
        if kind == "step":
            _, step, observed = item
            self.writer.append(step, self._ns(observed))
        elif kind == "frame":
            _, camera, image, captured, index = item
            time_ns = self._ns(captured)
            packet = self._encoders[camera].encode(image)
            message = CompressedVideo(frame_id=camera, format=FRAME_FORMAT, data=packet)
            message.timestamp.FromNanoseconds(time_ns)
            self.writer.write(CAMERA_PREFIX + camera, message, time_ns, index)
            self.counts[camera] += 1
        else:
            _, stream, received, rows, clock = item
            topic = SAMPLES_PREFIX + stream
            for host, row, source in zip(received, rows, clock, strict=True):
                time_ns = self._ns(float(host))
                vector = FloatVector(step=self.counts[stream], values=row.tolist())
                vector.timestamp.FromNanoseconds(round(float(source) * 1e9))
                self.writer.write(topic, vector, time_ns, self.counts[stream])
                self.counts[stream] += 1


def read_live_episode(path: str | Path, *, images: bool = True) -> contract.Episode:
    """An episode with its sample streams (``Episode.samples``; none for an episode of
    steps only). Only a real cell records them, so the twin's and the plant's episodes
    are not read twice."""
    episode = read_episode(path, images=images)
    if episode.meta.world != "real":
        return episode
    return replace(episode, samples=read_samples(path))


def read_samples(path: str | Path) -> dict[str, Samples]:
    """The sample streams of a live episode (none for an episode of steps only)."""
    from mcap.records import Channel, Message, Metadata

    from twinrl_data.mcap_log import _decode, _open_checked

    path = _open_checked(path)
    channels: dict[int, str] = {}
    rows: dict[str, list[tuple[int, float, list[float]]]] = {}
    records: dict[str, dict[str, Any]] = {}

    def damaged(_chunk: Any) -> None:
        raise DataError(f"{path} is damaged; `twinrl data recover {path}` rewrites what is intact")

    with open(path, "rb") as f:
        for record in intact_records(f, damaged):
            if isinstance(record, Channel) and record.topic.startswith(SAMPLES_PREFIX):
                channels[record.id] = record.topic[len(SAMPLES_PREFIX) :]
            elif isinstance(record, Message) and record.channel_id in channels:
                vector = FloatVector.FromString(record.data)
                stamp = vector.timestamp.seconds + vector.timestamp.nanos / 1e9
                rows.setdefault(channels[record.channel_id], []).append(
                    (record.log_time, stamp, list(vector.values))
                )
            elif isinstance(record, Metadata):
                records[record.name] = _decode(record.metadata)
    start = _iso_to_ns(records[META_START]["created_at"]) if META_START in records else 0
    names = records.get(META_STREAMS, {}).get("samples", {})
    streams = {}
    for stream, found in rows.items():
        found.sort()
        streams[stream] = Samples(
            names=list(names.get(stream, [])),
            times=np.array([(t - start) / 1e9 for t, _, _ in found]),
            values=np.array([v for _, _, v in found], np.float32),
            clock=np.array([c for _, c, _ in found]),
        )
    return streams
