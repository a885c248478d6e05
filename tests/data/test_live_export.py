"""A live episode exported to LeRobot at its cameras' rate: every frame of the first
camera a row, its logged frames copied into the videos, the state resampled from its
500 Hz stream, the control steps held."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from twinrl_data.catalog import build_index, load_selected, query
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.live_export import LIVE_INFO, LiveRows, encoder_config, read_live
from twinrl_data.live_video import VIDEO_OPTIONS, decode_frame
from twinrl_data.mcap_log import META_STREAMS, EpisodeWriter, _iso_to_ns, read_episode
from twinrl_data.salvage import recover
from twinrl_data.schema import STATE, EpisodeMeta, step_record
from twinrl_data.streams import LiveEpisode

START = 1000.0  # s, the host's monotonic clock when the episode starts
FPS, SERVO_HZ, CONTROL_HZ = 30, 500, 10
FRONT_AT = 0.005  # s, the front camera's first capture after the start
WRIST_AT = 0.020  # s, the wrist camera's


def _frame(value: int) -> np.ndarray:
    return np.full((48, 64, 3), value, np.uint8)


def record_live(path: Path, seconds: float = 1.0, dropped: tuple[int, ...] = ()) -> None:
    """A live episode: two 30 fps cameras (frame k of the front one 8k bright, of the
    wrist one 255 - 8k; the front's ``dropped`` frames never come), a 500 Hz state
    stream (its entries the sample's time), 10 Hz steps (step t's action t, its state
    -1)."""
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=CONTROL_HZ)
    meta = meta.replace(names={STATE: ["a", "b", "c"]})
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = EpisodeWriter(path, meta, flush_seconds=0)
    live = LiveEpisode(
        writer,
        cameras={"front": FPS, "wrist": FPS},
        samples={"controller": ["q.0"], STATE: ["a", "b", "c"]},
        started=START,
    )
    frames = round(seconds * FPS)
    for k in range(frames):
        if k not in dropped:
            live.frame("front", _frame(8 * k), START + FRONT_AT + k / FPS, k)
        live.frame("wrist", _frame(255 - 8 * k), START + WRIST_AT + k / FPS, k)
    times = np.arange(round(seconds * SERVO_HZ)) / SERVO_HZ
    for batch in np.array_split(np.arange(len(times)), 5):
        rows = np.repeat(times[batch, None], 3, axis=1).astype(np.float32)
        live.samples(STATE, START + times[batch], rows, times[batch])
        live.samples("controller", START + times[batch], rows[:, :1], times[batch])
    for t in range(round(seconds * CONTROL_HZ)):
        observation = {STATE: np.full(3, -1, np.float32), "observation.images.front": _frame(0)}
        action = np.full(7, t, np.float32)
        step = step_record(observation, action, np.zeros(6), 0.0, False, False)
        live.step(step, START + t / CONTROL_HZ)
    live.close()
    writer.close()


def test_a_live_episode_exports_every_frame_at_the_cameras_rate(tmp_path: Path) -> None:
    record_live(tmp_path / "live.mcap")
    result = export_dataset([read_live(tmp_path / "live.mcap")], tmp_path / "ds", repo_id="t/live")
    assert result.frames == FPS  # one row per front frame
    dataset = LeRobotDataset("t/live", root=tmp_path / "ds", video_backend="pyav")
    assert dataset.fps == FPS and dataset.num_frames == FPS
    # Each camera's video holds the rows' frames, encoded as recorded.
    for camera in ("front", "wrist"):
        (video,) = (tmp_path / "ds" / "videos" / f"observation.images.{camera}").rglob("*.mp4")
        with av.open(str(video)) as container:
            assert sum(1 for _ in container.decode(video=0)) == FPS
            assert container.streams.video[0].codec_context.name == "h264"
    info = json.loads((tmp_path / "ds" / LIVE_INFO).read_text())
    assert info["control_fps"] == CONTROL_HZ
    for i in (0, 1, 14, 29):
        row = dataset[i]
        captured = FRONT_AT + i / FPS  # the row's time on the episode's clock
        assert float(row["timestamp"]) == pytest.approx(i / FPS)
        # The state: the newest 500 Hz sample at or before the frame's capture.
        newest = np.floor(captured * SERVO_HZ + 1e-6) / SERVO_HZ
        np.testing.assert_allclose(row[STATE].numpy(), newest, atol=1e-6)
        # The action: the control step in force (step t observed at t / 10).
        assert row["action"].numpy()[0] == np.floor(captured * CONTROL_HZ)
        # The front camera's frame i; the wrist's newest frame captured by then.
        front = 255 * row["observation.images.front"].numpy().mean()
        assert front == pytest.approx(8 * i, abs=4)
        seen = max(0, int(np.floor((captured - WRIST_AT) * FPS + 1e-6)))
        wrist = 255 * row["observation.images.wrist"].numpy().mean()
        assert wrist == pytest.approx(255 - 8 * seen, abs=4)


def test_a_dropped_frame_is_the_frame_before_repeated_and_the_rows_keep_the_clock(
    tmp_path: Path,
) -> None:
    record_live(tmp_path / "live.mcap", dropped=(10,))
    rows = read_live(tmp_path / "live.mcap")
    assert len(rows) == FPS and set(rows.videos) == {"front", "wrist"}
    # Row 10 is frame 9 again, captured a period before its time; row 11 frame 11.
    np.testing.assert_allclose(rows.times[9:12], FRONT_AT + np.array([9, 9, 11]) / FPS)
    export_dataset([rows], tmp_path / "ds", repo_id="t/dropped")
    dataset = LeRobotDataset("t/dropped", root=tmp_path / "ds", video_backend="pyav")
    brightness = [255 * dataset[i]["observation.images.front"].numpy().mean() for i in (9, 10, 11)]
    np.testing.assert_allclose(brightness, [72, 72, 88], atol=4)
    assert float(dataset[11]["timestamp"]) == pytest.approx(11 / FPS)
    # The state is the robot's when the image was taken (frame 9's capture).
    newest = np.floor((FRONT_AT + 9 / FPS) * SERVO_HZ + 1e-6) / SERVO_HZ
    np.testing.assert_allclose(dataset[10][STATE].numpy(), newest, atol=1e-6)


def test_a_crashed_live_episode_exports_the_same_videos(tmp_path: Path) -> None:
    record_live(tmp_path / "live.mcap")
    # Recovery keeps the messages: the frames, encoded as they came, are the videos.
    recovered = recover(tmp_path / "live.mcap", tmp_path / "recovered.mcap").output
    rows = read_live(recovered)
    assert rows.videos == read_live(tmp_path / "live.mcap").videos
    assert rows.videos.keys() == {"front", "wrist"}
    export_dataset([rows], tmp_path / "ds", repo_id="t/recovered")
    dataset = LeRobotDataset("t/recovered", root=tmp_path / "ds", video_backend="pyav")
    assert dataset.num_frames == FPS
    front = 255 * dataset[14]["observation.images.front"].numpy().mean()
    assert front == pytest.approx(8 * 14, abs=4)


def test_live_and_step_rate_episodes_do_not_mix_in_one_dataset(tmp_path: Path) -> None:
    record_live(tmp_path / "live.mcap")
    rows = read_live(tmp_path / "live.mcap")
    steps = read_episode(tmp_path / "live.mcap")  # the same episode at its control rate
    with pytest.raises(DataError, match="10 fps, the first 30 fps.*cameras' rate"):
        export_dataset([rows, steps], tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_an_episode_of_steps_only_is_not_read_as_live(tmp_path: Path) -> None:
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=CONTROL_HZ)
    with EpisodeWriter(tmp_path / "steps.mcap", meta) as writer:
        observation = {STATE: np.zeros(3, np.float32)}
        writer.append(step_record(observation, np.zeros(7), np.zeros(6), 0.0, True, False))
    with pytest.raises(DataError, match="not a live episode.*control rate"):
        read_live(tmp_path / "steps.mcap")


def test_the_videos_are_encoded_with_the_settings_lerobot_is_told() -> None:
    assert encoder_config().get_codec_options(as_strings=True) == VIDEO_OPTIONS


def test_data_export_writes_a_live_episode_at_its_cameras_rate(tmp_path: Path) -> None:
    record_live(tmp_path / "live.mcap")
    run = subprocess.run(
        [sys.executable, "-m", "twinrl_learn", "data", "export", str(tmp_path / "live.mcap"),
         "--to", str(tmp_path / "ds")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert f"1 episodes, {FPS} frames" in run.stdout
    info = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert (
        info["fps"] == FPS
        and info["features"]["observation.images.front"]["info"]["video.codec"] == "h264"
    )


def test_a_catalog_selection_reads_live_episodes_as_rows_for_export(tmp_path: Path) -> None:
    record_live(tmp_path / "episodes" / "live.mcap")
    build_index([tmp_path / "episodes" / "live.mcap"], tmp_path / "catalog.parquet")
    table = query(tmp_path / "catalog.parquet")
    (rows,) = load_selected(table, live=True)
    assert isinstance(rows, LiveRows) and len(rows) == FPS
    (steps,) = load_selected(table)  # as episodes of steps everywhere else
    assert len(steps) == CONTROL_HZ


def test_a_cut_short_episode_file_is_refused_in_one_line_and_nothing_is_written(
    tmp_path: Path,
) -> None:
    record_live(tmp_path / "live.mcap")
    data = (tmp_path / "live.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    run = subprocess.run(
        [sys.executable, "-m", "twinrl_learn", "data", "export", str(tmp_path / "cut.mcap"),
         "--to", str(tmp_path / "ds")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode != 0 and not (tmp_path / "ds").exists()
    assert "truncated or damaged" in run.stderr and "twinrl data recover" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1


def test_the_videos_are_the_logged_frames_copied_not_encoded_again(tmp_path: Path) -> None:
    record_live(tmp_path / "live.mcap", dropped=(10,))
    rows = read_live(tmp_path / "live.mcap")
    for camera in ("front", "wrist"):
        with av.open(io.BytesIO(rows.videos[camera])) as container:
            decoded = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
        assert len(decoded) == len(rows)
        for t in (0, 9, 10, 29):  # row 10 repeats frame 9 of the front camera
            np.testing.assert_array_equal(decoded[t], decode_frame(rows.frames[camera][t]))


def test_a_live_episode_logged_with_jpeg_frames_still_exports(tmp_path: Path) -> None:
    """The log of a recorder from before the frames were H.264: JPEG frames, encoded at
    export."""
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=CONTROL_HZ)
    start_ns = 0
    with EpisodeWriter(tmp_path / "old.mcap", meta, flush_seconds=0) as writer:
        start_ns = _iso_to_ns(writer.meta.created_at)
        writer.add_metadata(META_STREAMS, {"cameras": {"front": FPS}, "samples": {}})
        for k in range(FPS):
            jpeg = cv2.imencode(".jpg", _frame(8 * k))[1].tobytes()
            time_ns = start_ns + round((FRONT_AT + k / FPS) * 1e9)
            writer.write("/camera/front", CompressedImage(format="jpeg", data=jpeg), time_ns, k)
        for t in range(CONTROL_HZ):
            observation = {STATE: np.full(3, t, np.float32)}
            step = step_record(
                observation, np.full(7, t, np.float32), np.zeros(6), 0.0, False, False
            )
            writer.append(step, start_ns + round(t / CONTROL_HZ * 1e9))
    rows = read_live(tmp_path / "old.mcap")
    assert len(rows) == FPS and rows.videos == {}
    export_dataset([rows], tmp_path / "ds", repo_id="t/old")
    dataset = LeRobotDataset("t/old", root=tmp_path / "ds", video_backend="pyav")
    front = 255 * dataset[14]["observation.images.front"].numpy().mean()
    assert dataset.num_frames == FPS and front == pytest.approx(8 * 14, abs=4)
