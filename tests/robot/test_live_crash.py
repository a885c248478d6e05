"""A recorder killed in the middle of a live episode on a UR cell: `twinrl data repair`
recovers the episode with at most a second of its camera frames and controller samples
lost."""

from __future__ import annotations

import datetime as dt
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.robot.test_live_recording import live_cell
from twinrl_data.live_export import read_live
from twinrl_data.mcap_log import read_summary
from twinrl_data.session import Session
from twinrl_data.streams import read_samples
from twinrl_robot.ur.emulator.harness import EmulatorProcess

pytestmark = pytest.mark.realtime
TWINRL = [sys.executable, "-m", "twinrl_learn"]


def _recording(out: Path) -> bool:
    try:
        entries = json.loads((out / "manifest.json").read_text())["episodes"]
    except (OSError, ValueError, KeyError):
        return False
    return [e["status"] for e in entries] == ["recording"]


def test_a_killed_live_recording_loses_at_most_a_second_of_frames_and_samples(
    tmp_path: Path,
) -> None:
    cell = live_cell(tmp_path)
    out = tmp_path / "session"
    with EmulatorProcess(cell, effects=None):
        recorder = subprocess.Popen(
            [*TWINRL, "record", "--robot", "ur", "--cell", str(cell), "--emulated",
             "--teleop", "scripted", "--no-keys", "--episodes", "1", "--max-steps", "600",
             "--out", str(out)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 120
            while not _recording(out) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _recording(out), "the episode did not start"
            time.sleep(4.0)
            recorder.send_signal(signal.SIGKILL)
            killed = time.time()
            recorder.wait()
        finally:
            recorder.kill()
    repaired = subprocess.run([*TWINRL, "data", "repair", str(out)], capture_output=True, text=True)
    assert repaired.returncode == 0 and "recovered 1" in repaired.stdout, repaired.stdout
    (path,) = Session(out).episode_paths()
    start = dt.datetime.fromisoformat(read_summary(path).meta.created_at).timestamp()
    frames = read_live(path).times  # the camera's frames, s from the episode's start
    samples = read_samples(path)
    last = {
        "frames": frames[-1],
        **{stream: found.times[-1] for stream, found in samples.items()},
    }
    assert set(last) == {"frames", "controller", "observation.state"}
    lost = {name: killed - (start + seconds) for name, seconds in last.items()}
    assert all(0 < seconds <= 1.0 for seconds in lost.values()), lost
    assert len(frames) > 30 and len(samples["controller"].times) > 500
