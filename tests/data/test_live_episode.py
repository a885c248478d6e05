"""Live episodes: steps, every camera frame (an H.264 keyframe each) and a 500 Hz sample
stream written from a background thread into one MCAP file, on one clock, and read back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo

from twinrl_data.errors import DataError
from twinrl_data.live_video import FrameEncoder, decode_frame, is_h264
from twinrl_data.mcap_log import EpisodeWriter, read_episode
from twinrl_data.schema import EpisodeMeta, step_record
from twinrl_data.streams import LiveEpisode, read_live_episode, read_samples

START = 1000.0  # s, the host's monotonic clock when the episode starts


def _frame(value: int) -> np.ndarray:
    return np.full((48, 64, 3), value, np.uint8)


def test_a_live_episode_keeps_every_frame_and_sample_on_the_steps_clock(tmp_path: Path) -> None:
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=10.0)
    writer = EpisodeWriter(tmp_path / "live.mcap", meta, flush_seconds=0)
    live = LiveEpisode(
        writer, cameras={"front": 30.0}, samples={"controller": ["q.0", "q.1"]}, started=START
    )
    for k in range(30):  # 1 s of a 30 fps camera
        live.frame("front", _frame(8 * k), START + k / 30, k + 1)
    clock = 50.0 + np.arange(500) / 500  # 1 s of the controller's own clock, at 500 Hz
    for batch in np.split(np.arange(500), 5):
        rows = np.stack([clock[batch], -clock[batch]], axis=1).astype(np.float32)
        live.samples("controller", START + clock[batch] - 50.0, rows, clock[batch])
    for t in range(10):  # 10 Hz steps; a step's own image of a streamed camera is not kept
        observation = {
            "observation.state": np.full(3, t, np.float32),
            "observation.images.front": _frame(255),
        }
        step = step_record(observation, np.zeros(7, np.float32), np.zeros(6), 0.0, t == 9, False)
        live.step(step, START + t / 10 + 0.001)
    live.close()
    writer.close()
    assert live.counts == {"front": 30, "controller": 500}
    episode = read_episode(tmp_path / "live.mcap")
    assert len(episode) == 10
    # Step t saw the newest frame captured by its time: frame 3t, 8 * 3t bright.
    brightness = episode.images["front"].reshape(10, -1).mean(axis=1)
    np.testing.assert_allclose(brightness, 24 * np.arange(10), atol=2)
    (samples,) = read_samples(tmp_path / "live.mcap").values()
    assert samples.names == ["q.0", "q.1"] and len(samples.values) == 500
    np.testing.assert_allclose(samples.times, np.arange(500) / 500, atol=1e-6)
    np.testing.assert_allclose(samples.clock, clock, atol=1e-6)
    np.testing.assert_allclose(samples.values[:, 0], clock, rtol=1e-6)
    # Read as an episode, the streams come with it when asked (the gap workflow does).
    assert not episode.samples
    streams = read_live_episode(tmp_path / "live.mcap", images=False).samples
    np.testing.assert_array_equal(streams["controller"].values, samples.values)


def test_a_step_that_breaks_the_contract_is_refused_where_it_is_given(tmp_path: Path) -> None:
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real")
    writer = EpisodeWriter(tmp_path / "live.mcap", meta, flush_seconds=0)
    live = LiveEpisode(writer, cameras={}, samples={}, started=START)
    with pytest.raises(Exception, match="missing"):
        live.step({"observation.state": np.zeros(3)}, START)
    live.close()
    writer.close()


def _textured(seed: int) -> np.ndarray:
    """A 640x480 picture with edges and noise, as a camera's."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    image = np.repeat(np.repeat(coarse, 16, axis=0), 16, axis=1).astype(np.int16)
    return np.clip(image + rng.normal(0, 4, image.shape), 0, 255).astype(np.uint8)


def test_each_logged_frame_is_an_h264_keyframe_that_decodes_on_its_own(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=10.0)
    writer = EpisodeWriter(tmp_path / "live.mcap", meta, flush_seconds=0)
    live = LiveEpisode(writer, cameras={"front": 30.0}, samples={}, started=START)
    pictures = [_textured(k) for k in range(4)]
    for k, picture in enumerate(pictures):
        live.frame("front", picture, START + k / 30, k)
    live.close()
    writer.close()
    with open(tmp_path / "live.mcap", "rb") as f:
        logged = [
            (schema.name, message.data)
            for schema, channel, message in make_reader(f).iter_messages(topics=["/camera/front"])
        ]
    assert [name for name, _ in logged] == ["foxglove.CompressedVideo"] * 4
    # Any one frame, read alone and out of order, is its picture (x264's crf 23 on noise).
    for k in (3, 0, 2):
        data = CompressedVideo.FromString(logged[k][1])
        assert data.format == "h264" and is_h264(data.data)
        error = np.abs(decode_frame(data.data).astype(int) - pictures[k]).mean()
        assert error < 6, error


def test_a_camera_of_odd_size_or_changing_size_is_refused_in_one_line(tmp_path: Path) -> None:
    encoder = FrameEncoder("front")
    with pytest.raises(DataError, match="camera front's frames are .*even width and height"):
        encoder.encode(np.zeros((479, 640, 3), np.uint8))
    encoder.encode(np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(DataError, match="frame 1 is \\(240, 320, 3\\), its first was"):
        encoder.encode(np.zeros((240, 320, 3), np.uint8))
    # In a recording, the next call says so and what was written stays readable.
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=10.0)
    writer = EpisodeWriter(tmp_path / "live.mcap", meta, flush_seconds=0)
    live = LiveEpisode(writer, cameras={"front": 30.0}, samples={}, started=START)
    live.frame("front", np.zeros((47, 64, 3), np.uint8), START, 0)
    with pytest.raises(DataError, match="the episode's writer stopped: camera front's frames"):
        live.close()
    writer.close()


def test_rerun_opens_a_live_episodes_cameras_as_video_streams(tmp_path: Path) -> None:
    from rerun.experimental import RrdReader

    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=10.0)
    writer = EpisodeWriter(tmp_path / "live.mcap", meta, flush_seconds=0)
    live = LiveEpisode(writer, cameras={"front": 30.0}, samples={}, started=START)
    for k in range(6):
        live.frame("front", _textured(k), START + k / 30, k)
    observation = {"observation.state": np.zeros(3, np.float32)}
    live.step(step_record(observation, np.zeros(7), np.zeros(6), 0.0, True, False), START)
    live.close()
    writer.close()
    rerun = Path(sys.executable).parent / "rerun"
    run = subprocess.run(
        [str(rerun), "mcap", "convert", str(tmp_path / "live.mcap"), "-o", str(tmp_path / "l.rrd")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    samples = [
        chunk.num_rows
        for chunk in RrdReader(tmp_path / "l.rrd").store().stream().to_chunks()
        if chunk.entity_path == "/camera/front"
        and "VideoStream:sample" in chunk.to_record_batch().schema.names
    ]
    assert sum(samples) == 6  # every frame, as Rerun's own video stream
