"""A live episode as LeRobot dataset frames at its cameras' rate.

A LeRobotDataset has one rate for everything in it. A live episode
(:mod:`twinrl_data.streams`) exports at its cameras' rate, so that every frame a camera
captured is in the video, rather than one frame per control step:

- **Rows**: one a period (``timestamp`` ``i / fps``) from the first frame of the
  episode's first camera (the *reference*); row ``i`` is the frame that camera had
  captured half a period after ``i / fps``: its ``i``-th frame when it delivers at its
  rate, the frame before repeated where it dropped one, so the rows keep the host's
  time. A row's *time* is its reference frame's capture. Every other camera gives each
  row the newest frame it had captured by then, as a policy running at that rate would
  have seen it (its first frame before it had any).
- **Observation state**: the newest sample of the episode's ``observation.state`` stream
  (the controller's every package, 500 Hz on a UR e-Series) taken at or before the
  row's time: at most one controller period older than the image, and what the robot
  reported at that moment, as a policy reads it when it runs. An average over the
  frame's period would lag the image by half a period and smooth the very motion the
  image shows; the nearest sample either side would read up to a millisecond ahead of
  it.
- **Everything else** (action, joint targets, efforts, reward, done, success): the
  control step in force at the row's time (the newest step observed by then), held
  over the rows of its period. ``action`` stays the command of one control period (a
  delta per control step): a policy trained on the rows predicts the command in force
  while it watches, and its outputs are sent at the control rate (every ``fps /
  control_fps`` rows); reward, done and success repeat on each row of their step.

The dataset says so in ``meta/twinrl/live.json`` (:data:`LIVE_INFO`; lerobot's own
``meta/info.json`` warns of any key it does not know), with the control rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data import schema as contract
from twinrl_data.errors import DataError
from twinrl_data.live_video import (
    VIDEO_CODEC,
    VIDEO_CRF,
    VIDEO_GOP,
    VIDEO_PIX_FMT,
    VIDEO_PRESET,
    decode_frame,
    is_h264,
    remux,
    row_count,
    row_time,
)
from twinrl_data.mcap_log import (
    CAMERA_PREFIX,
    CAMERA_SCHEMAS,
    META_START,
    META_STREAMS,
    TOPICS,
    _damaged,
    _decode,
    _iso_to_ns,
    _open_checked,
    intact_records,
    read_episode,
)
from twinrl_data.step_frames import frames_of_steps
from twinrl_data.streams import read_samples

LIVE_INFO = Path("meta") / "twinrl" / "live.json"


@dataclass(frozen=True)
class LiveRows:
    """A live episode at its cameras' rate (see the module docstring)."""

    episode: contract.Episode  # the fields at the rows (``meta.fps``: the rows' rate)
    control_fps: float  # the rate of its control steps
    reference: str  # the camera whose frames are the rows
    times: np.ndarray  # (rows,) s from the episode's start, host clock: each row's capture
    frames: dict[str, list[bytes]]  # each camera's logged frame at each row
    videos: dict[str, bytes]  # each camera's MP4 of the rows: its logged frames, remuxed

    def __len__(self) -> int:
        return len(self.times)

    def shape(self, camera: str) -> tuple[int, int, int]:
        """A camera's frame shape (H, W, 3)."""
        return decode_frame(self.frames[camera][0]).shape


def is_live(path: str | Path) -> bool:
    """Whether an episode file is a live episode with cameras (its metadata says so)."""
    from mcap.reader import make_reader

    path = _open_checked(path)
    try:
        with open(path, "rb") as f:
            streams = [m for m in make_reader(f).iter_metadata() if m.name == META_STREAMS]
    except Exception as err:
        raise _damaged(path, err) from None
    return any(_decode(m.metadata).get("cameras") for m in streams)


def read_for_export(path: str | Path) -> contract.Episode | LiveRows:
    """An episode file as it exports: a live episode's rows, else its steps."""
    return read_live(path) if is_live(path) else read_episode(path)


def read_live(path: str | Path) -> LiveRows:
    """A live episode's rows (:class:`LiveRows`); a damaged file is refused."""
    from mcap.records import Channel, Message, Metadata, Schema

    path = _open_checked(path)
    episode = read_episode(path, images=False)
    records: dict[str, dict[str, Any]] = {}
    schemas: dict[int, str] = {}  # schema id -> name
    channels: dict[int, tuple[str, str]] = {}  # channel id -> topic, its schema's name
    frames: dict[str, dict[int, tuple[int, bytes]]] = {}
    step_times: dict[int, int] = {}

    def damaged(_chunk: Any) -> None:
        raise DataError(f"{path} is damaged; `twinrl data recover {path}` rewrites what is intact")

    with open(path, "rb") as f:
        for record in intact_records(f, damaged):
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
            elif isinstance(record, Message):
                topic, schema = channels.get(record.channel_id, ("", ""))
                if topic == TOPICS[contract.STATE]:
                    step_times[record.sequence] = record.log_time
                elif topic.startswith(CAMERA_PREFIX):
                    image = CAMERA_SCHEMAS[schema].FromString(record.data).data
                    camera = topic[len(CAMERA_PREFIX) :]
                    frames.setdefault(camera, {})[record.sequence] = (record.log_time, image)
            elif isinstance(record, Metadata):
                records[record.name] = _decode(record.metadata)
    cameras = list(records.get(META_STREAMS, {}).get("cameras", {}))
    if not cameras or not all(frames.get(camera) for camera in cameras):
        raise DataError(
            f"{path} is not a live episode with camera frames; it exports at its control rate"
        )
    reference = cameras[0]
    start = _iso_to_ns(records[META_START]["created_at"])
    fps = round(float(records[META_STREAMS]["cameras"][reference]))
    ordered = sorted(frames[reference].values())
    captured = (np.array([t for t, _ in ordered]) - start) / 1e9
    count = row_count(captured[0], captured[-1], fps)
    ticks = [row_time(captured[0], row, fps) for row in range(count)]
    chosen = np.clip(np.searchsorted(captured, ticks, side="right") - 1, 0, None)
    times = captured[chosen]
    row_ns = [ordered[i][0] for i in chosen]
    steps_ns = np.array([step_times[s] for s in range(len(episode))])
    steps = np.clip(np.searchsorted(steps_ns, row_ns, side="right") - 1, 0, len(episode) - 1)
    samples = read_samples(path)
    data = {}
    for key, values in episode.data.items():
        if key in samples and samples[key].values.shape[1:] == values.shape[1:]:
            stream = samples[key]
            newest = np.clip(np.searchsorted(stream.times, times, side="right") - 1, 0, None)
            data[key] = stream.values[newest]
        else:
            data[key] = values[steps]
    rows = {
        camera: [image for _, image in frames_of_steps(frames[camera], row_ns).values()]
        for camera in cameras
    }
    rows[reference] = [ordered[i][1] for i in chosen]
    videos = {  # a log from before the frames were H.264 has JPEGs: export encodes them
        camera: remux(frames, fps) for camera, frames in rows.items() if all(map(is_h264, frames))
    }
    return LiveRows(
        episode=contract.Episode(meta=episode.meta.replace(fps=float(fps)), data=data),
        control_fps=episode.meta.fps,
        reference=reference,
        times=times,
        frames=rows,
        videos=videos,
    )


def live_info(rows: LiveRows) -> dict[str, Any]:
    """What a dataset of live episodes says about its rows (:data:`LIVE_INFO`)."""
    return {
        "rows": f"one a period: the newest frame of camera '{rows.reference}' half a period on",
        "row time": "that frame's capture, on the host's clock",
        "cameras": "each camera's newest frame captured by the row's time",
        "observation.state": "the newest controller sample at or before the row's time",
        "other fields": "the control step in force at the row's time (held over its rows)",
        "control_fps": rows.control_fps,
    }


def encoder_config() -> Any:
    """lerobot's encoder settings of the frames encoded while recording."""
    from lerobot.configs.video import RGBEncoderConfig

    return RGBEncoderConfig(
        vcodec=VIDEO_CODEC, pix_fmt=VIDEO_PIX_FMT, g=VIDEO_GOP, crf=VIDEO_CRF, preset=VIDEO_PRESET
    )


def video_stats(frames: list[bytes]) -> dict[str, np.ndarray]:
    """A camera's per-channel statistics over a sample of its frames, as lerobot's
    streaming encoder computes them over all of them."""
    from lerobot.datasets.compute_stats import (
        RunningQuantileStats,
        auto_downsample_height_width,
        sample_indices,
    )

    stats = RunningQuantileStats()
    for index in sample_indices(len(frames)):
        chw = decode_frame(frames[index]).transpose(2, 0, 1)
        small = auto_downsample_height_width(chw)
        stats.update(small.transpose(1, 2, 0).reshape(-1, small.shape[0]))
    return stats.get_statistics()


class LiveVideos:
    """lerobot's streaming video encoder, but for an episode whose videos were encoded
    while recording (:meth:`use`): those are handed over as they are."""

    def __init__(self) -> None:
        self.encoder: Any = None  # lerobot's StreamingVideoEncoder, for the other episodes
        self._ready: dict[str, tuple[bytes, dict[str, np.ndarray]]] | None = None
        self._temp: Path | None = None

    def use(self, videos: dict[str, tuple[bytes, dict[str, np.ndarray]]] | None) -> None:
        """The next episode's videos (feature key -> MP4, stats); ``None``: encode it."""
        self._ready = videos

    def start_episode(
        self, video_keys: list[str], temp_dir: Path, depth_video_keys: list[str] | None = None
    ) -> None:
        if self._ready is None:
            self.encoder.start_episode(video_keys, temp_dir, depth_video_keys)
        self._temp = Path(temp_dir)

    def feed_frame(self, video_key: str, image: np.ndarray) -> None:
        if self._ready is None:
            self.encoder.feed_frame(video_key, image)

    def finish_episode(self) -> dict[str, tuple[Path, dict | None]]:
        if self._ready is None:
            return self.encoder.finish_episode()
        import tempfile

        results = {}
        for key, (data, stats) in self._ready.items():
            folder = Path(tempfile.mkdtemp(dir=self._temp))  # lerobot removes it once moved
            path = folder / f"{key}.mp4"
            path.write_bytes(data)
            results[key] = (path, stats)
        self._ready = None
        return results

    def cancel_episode(self) -> None:
        self._ready = None
        self.encoder.cancel_episode()

    def close(self) -> None:
        self.encoder.close()


def live_dataset_class(videos: LiveVideos) -> type:
    """``LeRobotDataset`` whose streaming encoder is ``videos`` (wrapping lerobot's own)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.video_utils import StreamingVideoEncoder

    class LiveDataset(LeRobotDataset):
        @staticmethod
        def _build_streaming_encoder(
            fps: int, rgb_encoder: Any, depth_encoder: Any, queue_maxsize: int, threads: Any
        ) -> Any:
            videos.encoder = StreamingVideoEncoder(
                fps=fps,
                rgb_encoder=rgb_encoder,
                depth_encoder=depth_encoder,
                queue_maxsize=queue_maxsize,
                encoder_threads=threads,
            )
            return videos

    return LiveDataset
