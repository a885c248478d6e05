"""Recording on a UR cell at its sensors' rates: every camera frame and every package
of the controller's 500 Hz state in the episode's file, on the steps' clock, exported
to LeRobot at the camera's rate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.robot.test_ur_cell import write_cell
from twinrl_data.lerobot_io import export_dataset, open_dataset
from twinrl_data.live_export import read_live
from twinrl_data.mcap_log import read_episode
from twinrl_data.streams import read_samples
from twinrl_robot.record_settings import RecordSettings
from twinrl_robot.recording import run_recording
from twinrl_robot.ur.emulator.harness import EmulatorProcess
from twinrl_robot.ur.sensor_streams import controller_names

pytestmark = pytest.mark.realtime


def live_cell(tmp_path: Path) -> Path:
    """An emulated UR cell file with one 160x120 camera at 30 fps and a 10 Hz loop."""
    cell = write_cell(tmp_path)
    host = cell.read_text().split("host: ")[1].split()[0]
    camera = {"name": "front", "kind": "opencv", "source": f"http://{host}:8080/front",
              "width": 160, "height": 120, "fps": 30}  # fmt: skip
    return write_cell(tmp_path, cameras=[camera], arm={"model": "ur5e", "host": host,
                      "control_hz": 10})  # fmt: skip


def step_clock(path: Path, created_at: str) -> np.ndarray:
    """Each step's log time (its state message's) in seconds from ``created_at``."""
    from mcap.reader import make_reader

    from twinrl_data.mcap_log import TOPICS, _iso_to_ns

    with open(path, "rb") as f:
        messages = make_reader(f).iter_messages([TOPICS["observation.state"]])
        return np.array([m.log_time for _, _, m in messages]) / 1e9 - _iso_to_ns(created_at) / 1e9


def test_a_ur_episode_holds_every_frame_and_controller_package_on_one_clock(
    tmp_path: Path,
) -> None:
    cell = live_cell(tmp_path)
    with EmulatorProcess(cell, effects=None):
        report = run_recording(
            RecordSettings(
                str(tmp_path / "s"), robot="ur", cell=str(cell), emulated=True,
                teleop="scripted", episodes=1, keys=False, max_steps=30,
            )
        )  # fmt: skip
    path = report.episodes[0].path
    episode = read_episode(path)
    streams = read_samples(path)
    samples, state = streams["controller"], streams["observation.state"]
    assert samples.names == controller_names()
    # The observation's state at the same rate: each package's joints, the TCP from them.
    assert state.names == episode.meta.names["observation.state"]
    np.testing.assert_array_equal(state.values[:, :12], samples.values[:, :12])
    # Every package once, in order, on the controller's 2 ms cycle.
    cycles = np.round(np.diff(samples.clock) * 500)
    assert (cycles >= 1).all() and np.allclose(np.diff(samples.clock) * 500, cycles, atol=0.01)
    # One clock: the 500 Hz state spans the steps, and its joints agree with each step's.
    steps = len(episode)
    # When each step was logged: its controller package's time on the samples' clock, so
    # a loaded host that reads it late does not shift it (stamped on reading, a step
    # was 0.13 rad away from the state logged beside it at the arm's 0.85 rad/s).
    stepped = step_clock(path, episode.meta.created_at)
    assert len(stepped) == steps and samples.times[0] < 0.2 and samples.times[-1] > stepped[-2]
    step_q = episode.data["observation.state"][:, :6]
    nearest = np.abs(samples.times[:, None] - stepped[None, :]).argmin(axis=0)
    # Each step beside its own package, or one a few servo periods away: ur_rtde's file
    # skips a package now and then, a frame captured after the package moves the step
    # to the frame's time, and the clocks' offset is found as the session goes, the
    # packages kept in order as it falls (12 ms seen in the first steps). The first
    # step's package came before the episode's start.
    assert np.abs(samples.times[nearest] - stepped)[1:].max() < 0.02
    assert np.abs(samples.values[nearest, :6] - step_q).max() < 0.03  # 20 ms at 1.5 rad/s
    step_tcp = episode.data["observation.state"][:, 12:19]  # and the TCP computed from them
    assert np.abs(state.values[nearest, 12:19] - step_tcp).max() < 0.03  # as the joints
    # The camera: each step given the frame it saw.
    assert episode.images["front"].shape == (steps, 120, 160, 3)
    # Exported at the camera's rate: every frame a row, the video encoded while recording.
    rows = read_live(path)
    assert set(rows.videos) == {"front"} and len(rows) > 2 * steps
    result = export_dataset([rows], tmp_path / "dataset", repo_id="tests/live")
    dataset = open_dataset(result.root)
    assert dataset.fps == 30 and dataset.num_frames == len(rows)
    row = dataset[len(rows) // 2]
    newest = np.searchsorted(state.times, rows.times[len(rows) // 2], side="right") - 1
    np.testing.assert_allclose(row["observation.state"].numpy(), state.values[newest])
