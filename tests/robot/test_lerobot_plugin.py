"""LeRobot's own commands on a twinrl UR cell, through the plugin: ``lerobot-record``
driven by a recorded SpaceMouse, ``lerobot-replay`` of what it recorded and
``lerobot-teleoperate`` from a recorded gamepad, all against the emulator and through the
cell's safety limits; the dataset opens in plain lerobot and in twinrl's tools; bad
input is one line."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.robot.test_ur_cell import EMULATED, write_cell
from tests.robot.test_ur_devices import host_of
from twinrl_robot.ur.emulator import free_loopback_host
from twinrl_robot.ur.emulator.harness import EmulatorProcess, HarnessClient
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell, state_names
from twinrl_sim.tasks import make_task

PLUGIN = "twinrl_robot.lerobot_plugin"
BIN = Path(sys.executable).parent
STEP_LIMIT = 0.01  # m per control step: the cell's limit, below the device map's 0.015


def plugin_args(*, robot: bool = True, teleop: bool = True) -> list[str]:
    args = [f"--robot.discover_packages_path={PLUGIN}"] if robot else []
    return args + ([f"--teleop.discover_packages_path={PLUGIN}"] if teleop else [])


def offline(home: Path) -> dict[str, str]:
    """The environment of a command that must not reach the network (caches in ``home``)."""
    return {**os.environ, "HF_HOME": str(home), "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1"}


def run(command: list[str], home: Path) -> None:
    """Run a command offline; it must succeed."""
    done = subprocess.run(command, env=offline(home), capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, f"{command[0]}:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"


def lerobot(command: str, *args: str, home: Path) -> None:
    run([str(BIN / command), *args], home)


def camera_cell(folder: Path) -> Path:
    """An emulated cell with a small front camera, a tight step limit and a SpaceMouse
    map of its own."""
    host = free_loopback_host()
    url = f"http://{host}:8080/front"
    return write_cell(
        folder,
        arm={"model": "ur5e", "host": host, "control_hz": 10},
        cameras=[{"name": "front", "source": url, "width": 64, "height": 48, "fps": 10}],
        safety={"max_step_translation": STEP_LIMIT},
        teleop={"spacemouse": {"translation": 0.015}},
    )


def spacemouse_pushing_x(path: Path, seconds: float = 60.0) -> Path:
    """A SpaceMouse Wireless recording: the cap pushed fully along +x, reported at 20 Hz."""
    report = (bytes([1]) + struct.pack("<6h", 350, 0, 0, 0, 0, 0)).hex()
    lines = [json.dumps({"device": "SpaceMouseWireless"})]
    lines += [json.dumps({"t": i / 20, "report": report}) for i in range(int(seconds * 20))]
    path.write_text("\n".join(lines) + "\n")
    return path


def gamepad_pushing_forward(path: Path) -> Path:
    """A gamepad recording: the deadman held and the left stick fully up (+x) from t=0."""
    lines = [
        {"ranges": {"ABS_X": [-32768, 32767], "ABS_Y": [-32768, 32767]}},
        {"t": 0.0, "type": "EV_KEY", "code": "BTN_TL", "value": 1},
        {"t": 0.0, "type": "EV_ABS", "code": "ABS_Y", "value": -32768},
    ]
    path.write_text("\n".join(map(json.dumps, lines)) + "\n")
    return path


def tcp_x(q: list[float]) -> float:
    cell = Cell(compile_scene(make_task("pick_place").scene))
    return float(cell.controller.forward(np.array(q))[0][0])


def test_the_configs_register_with_lerobot_and_name_the_cells_features(tmp_path: Path) -> None:
    from lerobot.configs.parser import load_plugin
    from lerobot.robots import RobotConfig, make_robot_from_config
    from lerobot.teleoperators import TeleoperatorConfig, make_teleoperator_from_config
    from lerobot.utils.feature_utils import hw_to_dataset_features

    load_plugin(PLUGIN)  # what --robot.discover_packages_path does
    cell = camera_cell(tmp_path)
    robot_config = RobotConfig.get_choice_class("twinrl_ur")(cell=cell, calibration_dir=tmp_path)
    robot = make_robot_from_config(robot_config)
    assert type(robot).__name__ == "TwinrlUR" and not robot.is_connected
    joints = compile_scene(make_task("pick_place").scene).layout.arm_joints
    names = state_names(joints)
    assert robot.observation_features == {**dict.fromkeys(names, float), "front": (48, 64, 3)}
    assert list(robot.action_features) == ["dx", "dy", "dz", "rx", "ry", "rz", "gripper"]
    dataset = hw_to_dataset_features(robot.observation_features, "observation")
    assert dataset["observation.state"]["names"] == names  # twinrl's contract, as recorded
    assert dataset["observation.images.front"]["shape"] == (48, 64, 3)
    no_camera = make_robot_from_config(
        RobotConfig.get_choice_class("twinrl_ur")(cell=cell, cameras=[], calibration_dir=tmp_path)
    )
    assert "front" not in no_camera.observation_features
    for kind, translation in (("spacemouse", 0.015), ("gamepad", 0.02)):
        config = TeleoperatorConfig.get_choice_class(f"twinrl_{kind}")(
            cell=cell, calibration_dir=tmp_path
        )
        teleop = make_teleoperator_from_config(config)
        assert teleop.action_features == robot.action_features
        assert teleop.map.translation == translation  # the cell file's map, or the default


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--robot.cell=absent.yaml"], "error: --robot: cell file absent.yaml does not exist"),
        (["--robot.cameras=[wrist]"], "error: --robot: camera(s) wrist are not in the cell file"),
        (["--teleop.recorded=absent.jsonl"], "error: --teleop.recorded: absent.jsonl does not"),
    ],
    ids=["missing cell file", "unknown camera", "missing recording"],
)
def test_bad_input_is_one_line(tmp_path: Path, args: list[str], said: str) -> None:
    cell = camera_cell(tmp_path)
    command = [
        str(BIN / "lerobot-teleoperate"),
        *plugin_args(),
        "--robot.type=twinrl_ur",
        f"--robot.cell={cell}",
        "--teleop.type=twinrl_gamepad",
        *args,
    ]
    done = subprocess.run(
        command, env=offline(tmp_path / "hf"), capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 1
    assert done.stderr.strip().startswith(said) and "\n" not in done.stderr.strip(), done.stderr


def emulated(test):
    """The emulator tests' marks: realtime, Linux's loopback addresses."""
    for mark in EMULATED:
        test = mark(test)
    return test


@emulated
def test_lerobot_records_and_replays_the_emulated_cell_and_twinrl_reads_the_dataset(
    tmp_path: Path,
) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    cell = camera_cell(tmp_path)
    recording = spacemouse_pushing_x(tmp_path / "spacemouse.jsonl")
    root, home = tmp_path / "dataset", tmp_path / "hf"
    robot_args = ["--robot.type=twinrl_ur", f"--robot.cell={cell}", "--robot.emulated=true"]
    with EmulatorProcess(cell):
        harness = HarnessClient(host_of(cell))
        try:
            lerobot(
                "lerobot-record",
                *plugin_args(),
                *robot_args,
                "--teleop.type=twinrl_spacemouse",
                f"--teleop.cell={cell}",
                f"--teleop.recorded={recording}",
                "--dataset.repo_id=tests/ur_push",
                f"--dataset.root={root}",
                "--dataset.fps=10",
                "--dataset.single_task=push along x",
                "--dataset.num_episodes=1",
                "--dataset.episode_time_s=2",
                "--dataset.push_to_hub=false",
                "--play_sounds=false",
                home=home,
            )
            dataset = LeRobotDataset("tests/ur_push", root=root, video_backend="pyav")
            start = tcp_x(harness.reading()["q"])  # where the recording left the arm
            lerobot(
                "lerobot-replay",
                *plugin_args(teleop=False),
                *robot_args,
                "--dataset.repo_id=tests/ur_push",
                f"--dataset.root={root}",
                "--dataset.episode=0",
                "--play_sounds=false",
                home=home,
            )
            replayed = tcp_x(harness.reading()["q"])
        finally:
            harness.close()

    assert dataset.meta.total_episodes == 1 and 10 <= dataset.num_frames <= 21
    assert dataset.meta.robot_type == "twinrl_ur" and dataset.fps == 10
    features = dataset.features
    joints = compile_scene(make_task("pick_place").scene).layout.arm_joints
    assert features["observation.state"]["names"] == state_names(joints)
    assert features["action"]["names"] == ["dx", "dy", "dz", "rx", "ry", "rz", "gripper"]
    assert features["observation.images.front"]["dtype"] == "video"
    assert dataset[0]["observation.images.front"].shape == (3, 48, 64)
    columns = dataset.hf_dataset.with_format("numpy")[:]
    state, action = np.stack(columns["observation.state"]), np.stack(columns["action"])
    # The teleoperator's action (the cell file's map: 0.015 m a step) is what lerobot
    # stores; the arm moved by the cell's safety limit (0.01 m a step) instead.
    np.testing.assert_allclose(action[:, :3], [[0.015, 0, 0]] * len(action), atol=1e-6)
    # Each observation is sampled a few ms off the period's end, so single steps jitter;
    # their mean after the start-up is the limit's (the device's would be 1.5 times it).
    stride = np.diff(state[:, 12])[2:].mean()  # tcp.x
    assert 0.9 * STEP_LIMIT < stride < 1.1 * STEP_LIMIT, stride
    # The replay went back to the start pose and pushed along x again.
    assert abs(replayed - start) < 0.03 and replayed - state[0, 12] > 0.1

    twinrl = [sys.executable, "-m", "twinrl_learn"]
    rrd, catalog = tmp_path / "view.rrd", tmp_path / "catalog.parquet"
    for command in (
        ["view", str(root), "--save", str(rrd), "--twin", str(cell)],
        ["data", "index", str(root), "--catalog", str(catalog)],
    ):
        run(twinrl + command, home)
    assert rrd.stat().st_size > 10_000
    import pyarrow.parquet as pq

    (row,) = pq.read_table(catalog).to_pylist()
    assert row["robot"] == "twinrl_ur" and row["world"] == "real" and row["kind"] == "lerobot"
    assert row["length"] == dataset.num_frames and row["cameras"] == "front"


@emulated
def test_lerobot_teleoperates_the_emulated_cell_from_a_gamepad(tmp_path: Path) -> None:
    cell = write_cell(tmp_path)
    recording = gamepad_pushing_forward(tmp_path / "gamepad.jsonl")
    with EmulatorProcess(cell):
        harness = HarnessClient(host_of(cell))
        try:
            before = tcp_x(harness.reading()["q"])
            lerobot(
                "lerobot-teleoperate",
                *plugin_args(),
                "--robot.type=twinrl_ur",
                f"--robot.cell={cell}",
                "--teleop.type=twinrl_gamepad",
                f"--teleop.recorded={recording}",
                "--fps=10",
                "--teleop_time_s=1.5",
                home=tmp_path / "hf",
            )
            reading = harness.reading()
        finally:
            harness.close()
    assert reading["program_running"] is False  # disconnect stopped the control program
    assert tcp_x(reading["q"]) - before > 0.1  # 15 steps of the stick's 0.02 m
