"""``twinrl record`` end to end without a person: a scripted person at a virtual device
records in the plant and on the emulator, with every mark; a killed recorder loses at
most a second and its session continues; bad input is one line and loses nothing."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.robot.test_ur_cell import write_cell
from tests.test_cli import twinrl
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.mcap_log import read_episode, read_summary
from twinrl_data.schema import CONTROLLER_TARGET, CONTROLLER_TIME, JOINT_TARGET
from twinrl_data.session import Session
from twinrl_data.sources import open_episode
from twinrl_robot.backends import open_robot
from twinrl_robot.record_settings import RecordSettings
from twinrl_robot.recording import record_session, run_recording
from twinrl_robot.reset_plan import ResetPlan
from twinrl_robot.teleop import TeleopError, open_teleop
from twinrl_robot.teleop.teleop import Teleop
from twinrl_robot.ur.emulator.harness import EmulatorProcess
from twinrl_sim.tasks import make_task

pytestmark = pytest.mark.realtime  # a person drives at the control rate: ~5 s an episode
TWINRL = [sys.executable, "-m", "twinrl_learn"]


def _outcomes(report) -> list[str]:
    return [e.outcome for e in report.episodes]


def test_a_scripted_person_records_in_the_plant_with_every_mark(tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    view = tmp_path / "live.rrd"
    report = run_recording(
        RecordSettings(
            str(tmp_path / "day1"),
            teleop="scripted",
            episodes=3,
            keys=False,
            save_view=str(view),
            marks=("discard", "success", "failure"),
        )
    )
    # The discarded episode was recorded again from the same configuration.
    assert _outcomes(report) == ["success", "failure", "success"]
    assert len(report.discarded) == 1 and Path(report.discarded[0]).parent.name == "discarded"
    session = Session(tmp_path / "day1")
    assert [e["status"] for e in session.entries] == ["complete"] * 3 and not session.problems
    episodes = [read_episode(p) for p in session.episode_paths()]
    first = episodes[0]
    assert first.meta.source == "teleop" and first.meta.operator == "scripted"
    assert first.meta.config == read_summary(report.discarded[0]).meta.config
    assert "observation.environment_state" in first.data  # the plant's poses, recorded too
    assert [e.meta.success for e in episodes] == [True, False, True]
    assert view.stat().st_size > 100_000  # cameras, guidance, plots
    # The cell in 3D: its shapes once, its bodies moved by the live joints and poses.
    from rerun.experimental import RrdReader

    entities = {c.entity_path: c for c in RrdReader(view).store().stream().to_chunks()}
    assert "/world/cell/link3/0" in entities and "/world/cell/banana/0" in entities
    assert "/signals/grasp/opening" in entities  # the fingers, as they open and close
    moved = [c for path, c in entities.items() if path == "/world/cell/link3"]
    assert moved and not moved[0].is_static
    result = export_dataset(episodes, tmp_path / "dataset", repo_id="tests/day1")
    dataset = LeRobotDataset("tests/day1", root=result.root, video_backend="pyav")
    assert dataset.meta.total_episodes == 3 and len(dataset) == sum(len(e) for e in episodes)


def test_a_scripted_person_records_on_the_emulated_arm(tmp_path: Path) -> None:
    cell = write_cell(tmp_path)
    with EmulatorProcess(cell, effects=None):
        report = run_recording(
            RecordSettings(
                str(tmp_path / "ur"),
                robot="ur",
                cell=str(cell),
                emulated=True,
                teleop="scripted",
                episodes=2,
                keys=False,
                marks=("failure",),
            )
        )
    assert _outcomes(report) == ["failure", "success"]
    episode = read_episode(report.episodes[1].path, images=False)
    assert episode.meta.world == "real" and episode.meta.success
    assert episode.data["intervention"].sum() == 0  # the person drove: no takeover
    # Each step carries the controller's own clock, from the episode's start: a control
    # period apart (10 Hz), whatever the host's clock did.
    clock = episode.data[CONTROLLER_TIME][:, 0].astype(float)
    assert episode.meta.names[CONTROLLER_TIME] == ["controller.t"]
    assert 0.0 <= clock[0] < 0.05
    assert np.median(np.diff(clock)) == pytest.approx(0.1, abs=0.01)
    # ... and the targets the controller was tracking then: the step's sent target, all
    # but the last milliseconds of its segment, the link's latency (a few ms on a quiet
    # host, 15 on a loaded two-core one; a 10 Hz step's target within 25 %; a step
    # logged a period off would be a whole segment away).
    echoed, sent = episode.data[CONTROLLER_TARGET], episode.data[JOINT_TARGET]
    assert episode.meta.names[CONTROLLER_TARGET] == episode.meta.names[JOINT_TARGET]
    moved = np.linalg.norm(sent[1:-1] - sent[:-2], axis=1) > 0.01
    short = np.linalg.norm(sent[1:-1] - echoed[2:], axis=1)[moved]
    assert np.median(short / np.linalg.norm(sent[1:-1] - sent[:-2], axis=1)[moved]) < 0.25
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    result = export_dataset([episode], tmp_path / "dataset", repo_id="tests/ur")
    dataset = LeRobotDataset("tests/ur", root=result.root, video_backend="pyav")
    assert dataset.meta.features[CONTROLLER_TIME]["names"] == ["controller.t"]
    assert float(dataset[3][CONTROLLER_TIME]) == pytest.approx(clock[3], abs=1e-4)
    back = open_episode(f"{result.root}#0")
    np.testing.assert_allclose(back.data[CONTROLLER_TIME][:, 0], clock, atol=1e-6)


def _manifest(folder: Path) -> list[dict]:
    try:
        return json.loads((folder / "manifest.json").read_text())["episodes"]
    except (OSError, ValueError, KeyError):
        return []


def test_a_killed_recorder_loses_at_most_a_second_and_the_session_continues(
    tmp_path: Path,
) -> None:
    out = tmp_path / "session"
    command = [*TWINRL, "record", "--out", str(out), "--teleop", "scripted", "--no-keys"]
    recorder = subprocess.Popen(
        [*command, "--episodes", "3"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 120
    while len(_manifest(out)) < 2 and time.monotonic() < deadline:  # the second episode starts
        time.sleep(0.05)
    started = time.monotonic()
    time.sleep(3.0)
    recorder.send_signal(signal.SIGKILL)
    recorder.wait()
    killed_after = time.monotonic() - started
    entries = _manifest(out)
    assert [e["status"] for e in entries] == ["complete", "recording"]
    # The next run recovers the open episode first, then numbers on after it.
    finished = subprocess.run(
        [*command, "--episodes", "1"], stdin=subprocess.DEVNULL, capture_output=True, text=True
    )
    assert finished.returncode == 0, finished.stderr
    assert "recovered first" in finished.stdout
    session = Session(out)
    assert [e["status"] for e in session.entries] == ["complete", "recovered", "complete"]
    assert [Path(e["file"]).name[:6] for e in session.entries] == ["000000", "000001", "000002"]
    partial = session.entries[1]["length"]
    fps = 10.0
    # At most a second lost, beyond the moments before its first step (the reset).
    assert partial >= (killed_after - 1.0 - 0.5) * fps, (partial, killed_after)


def _run(*args: str, stdin=subprocess.DEVNULL) -> subprocess.CompletedProcess:
    return subprocess.run([*TWINRL, *args], stdin=stdin, capture_output=True, text=True)


def test_bad_input_is_one_line_and_loses_nothing(tmp_path: Path) -> None:
    out = tmp_path / "kept"
    assert (
        _run("record", "--out", str(out), "--teleop", "scripted", "--episodes", "1").returncode == 0
    )
    before = sorted(p.name for p in (out / "episodes").iterdir())
    for args, message in [
        (("--teleop", "spacemouse"), "no SpaceMouse is plugged in"),
        (("--teleop", "keyboard"), "the keyboard device reads the terminal's keys"),
        (("--teleop", "joystick"), "unknown teleop device 'joystick'"),
        (("--plan", "elsewhere"), "neither a region"),
        (("--robot", "ur"), "needs its cell file"),
    ]:
        result = twinrl("record", "--out", str(out), *args, cwd=tmp_path)
        assert result.returncode == 2, (args, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (args, result.stderr)
    assert sorted(p.name for p in (out / "episodes").iterdir()) == before
    assert not Session(out).problems


class _Unplugged:
    """A scripted person whose device goes away after ``reads`` reads."""

    def __init__(self, inner, reads: int) -> None:
        self.inner, self.reads = inner, reads
        self.kind, self.continuous = inner.kind, inner.continuous

    def read(self, observation=None):
        self.reads -= 1
        if self.reads < 0:
            raise TeleopError("the SpaceMouse stopped answering (unplugged); the arm holds")
        return self.inner.read(observation)

    def episode(self, task, config) -> None:
        self.inner.episode(task, config)

    def close(self) -> None:
        self.inner.close()


def test_a_device_lost_mid_episode_holds_the_arm_and_keeps_the_episode(tmp_path: Path) -> None:
    task = make_task("pick_place")
    robot = open_robot("plant", task, cameras=("front",), seed=0)
    session = Session.create(tmp_path / "s")
    scripted = open_teleop("scripted", privileged=robot.privileged)
    teleop = Teleop(_Unplugged(scripted.device, reads=15), scripted.map)
    try:
        with pytest.raises(TeleopError, match="unplugged"):
            record_session(robot, task, teleop, session, episodes=1, plan=ResetPlan(task, "ID"))
    finally:
        robot.close()
    session.refresh()
    (entry,) = session.entries
    summary = read_summary(session.path / entry["file"])
    assert entry["status"] == "complete" and 5 <= summary.length <= 15
    assert "unplugged" in summary.meta.aborted


def test_a_full_disk_refuses_the_episode_before_it_starts(tmp_path: Path) -> None:
    task = make_task("pick_place")
    robot = open_robot("plant", task, seed=0)
    session = Session(Session.create(tmp_path / "s").path, min_free=2**62)
    teleop = open_teleop("scripted", privileged=robot.privileged)
    try:
        with pytest.raises(Exception, match="free"):
            record_session(robot, task, teleop, session, episodes=1, plan=ResetPlan(task, "ID"))
    finally:
        robot.close()
    assert not list((session.path / "episodes").iterdir())


def _read_until(fd: int, text: str, seen: bytearray, timeout: float = 120.0) -> None:
    """Read the pseudo-terminal until ``text`` has been printed."""
    import select

    deadline = time.monotonic() + timeout
    while text not in re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", seen.decode(errors="replace")):
        assert time.monotonic() < deadline, f"{text!r} never showed: {seen[-400:]!r}"
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            seen += os.read(fd, 4096)


def test_the_terminal_keys_mark_and_annotate_episodes(tmp_path: Path) -> None:
    import pty

    out = tmp_path / "keys"
    leader, follower = pty.openpty()
    recorder = subprocess.Popen(
        [*TWINRL, "record", "--out", str(out), "--teleop", "scripted", "--episodes", "2"],
        stdin=follower,
        stdout=follower,
        stderr=follower,
        close_fds=True,
    )
    os.close(follower)
    seen = bytearray()
    try:
        _read_until(leader, "episode 1/2 | recording", seen)
        os.write(leader, b"nfirst try\r")  # a note, typed while the arm moves
        _read_until(leader, "episode 2/2 | recording", seen)
        os.write(leader, b"f")  # failure, before the person's success
        assert recorder.wait(timeout=120) == 0, seen[-2000:]
    finally:
        recorder.kill()
        os.close(leader)
    first, second = (read_summary(p).meta for p in Session(out).episode_paths())
    assert first.note == "first try" and first.success
    assert second.note is None and second.success is False
