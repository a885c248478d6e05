"""``twinrl record``'s settings record: its options derive from it, and every bad value
is one line naming the setting (by its flag on the command line); nothing is written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from twinrl_data.errors import SettingError
from twinrl_data.settings_cli import describe, options
from twinrl_robot.record_settings import RecordSettings
from twinrl_sim.errors import TwinError


def test_the_live_view_goes_where_one_setting_says() -> None:
    assert RecordSettings("s").view is None
    assert RecordSettings("s", viewer=True).view == "spawn"
    assert RecordSettings("s", connect="rerun+http://h:9876/proxy").view.startswith("rerun+")
    assert RecordSettings("s", save_view="live.rrd").view == "live.rrd"


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"robot": "kuka"}, "robot 'kuka' is unknown; record on plant or ur"),
        ({"robot": "ur"}, "cell is missing: recording on a UR arm needs its cell file"),
        ({"cell": "cell.yaml"}, "cell describes a UR arm; record on it with `robot` ur"),
        ({"emulated": True}, "emulated names a UR cell's emulator"),
        ({"robot": "ur", "cell": "c.yaml", "effects": "e.yaml"}, "effects apply to the plant"),
        ({"episodes": 0}, "episodes must be at least 1, got 0"),
        ({"settle": -1}, "settle must be at least 0, got -1"),
        ({"max_steps": 0}, "max_steps must be at least 1, got 0"),
        ({"viewer": True, "save_view": "a.rrd"}, "save_view goes with `viewer`"),
        ({"save_view": "live.txt"}, "save_view must name a .rrd file, got live.txt"),
        ({"viewer": True, "web": True}, "web goes with `viewer`"),
        ({"bind": "0.0.0.0"}, "bind goes with `web`: it is where the web viewer listens"),
        ({"web": True, "grpc_port": 0}, "grpc_port must be a port, 1 to 65535, got 0"),
    ],
)
def test_a_bad_setting_is_refused_by_name(changes: dict, message: str) -> None:
    with pytest.raises(SettingError) as caught:
        RecordSettings("s", **changes)
    assert message in str(caught.value)


def test_an_unknown_task_suggests_the_nearest() -> None:
    with pytest.raises(TwinError, match="did you mean 'pick_place'"):
        RecordSettings("s", task="pick_plac")


def test_every_option_derives_from_the_record_and_errors_name_flags() -> None:
    names = {option.name for option in options(RecordSettings)}
    assert {"out", "save_view", "max_steps", "viewer", "connect"} <= names
    with pytest.raises(SettingError) as caught:
        RecordSettings("s", viewer=True, save_view="a.rrd")
    assert (
        describe(caught.value)
        == "--save-view goes with --viewer; the live view goes to one of them"
    )


def test_the_command_line_refuses_a_bad_value_in_one_line_and_writes_nothing(
    tmp_path: Path,
) -> None:
    out = tmp_path / "session"
    for args, message in [
        (("--episodes", "0"), "--episodes must be at least 1, got 0"),
        (("--save-view", "live.txt"), "--save-view must name a .rrd file"),
        (("--robot", "ur"), "--cell is missing"),
    ]:
        result = subprocess.run(
            [sys.executable, "-m", "twinrl_learn", "record", "--out", str(out), *args],
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
        )
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1 and message in lines[0], result.stderr
    assert not out.exists()


def test_a_web_port_in_use_is_one_line_before_anything_is_written(tmp_path: Path) -> None:
    import socket

    out = tmp_path / "session"
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "twinrl_learn", "record", "--out", str(out), "--web",
             "--web-port", str(port), "--teleop", "scripted", "--no-keys"],
            stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert f"port {port} on 127.0.0.1 is in use; choose another --web-port" in lines[0]
    assert not out.exists()
