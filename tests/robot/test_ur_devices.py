"""A real cell's devices against the emulator (the Robotiq socket, a digital-output
gripper through ur_rtde's I/O interface, MJPEG cameras through OpenCV), the stops the
driver names in one line, and the one-line errors of a cell that cannot be reached."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.robot.test_ur_cell import write_cell
from tests.test_cli import twinrl_process
from twinrl_robot.backends import open_robot
from twinrl_robot.errors import RobotError
from twinrl_robot.ur.cameras import CameraError, CameraRig, CameraStats, Frame, OpenCVCamera
from twinrl_robot.ur.driver import RobotConnectionError, RobotStopped
from twinrl_robot.ur.emulator.harness import EmulatorProcess, HarnessClient
from twinrl_robot.ur.gripper import DigitalGripper, RobotiqGripper
from twinrl_sim.tasks import make_task

pytestmark = pytest.mark.realtime  # the emulator and the cameras keep real time


def host_of(cell: Path) -> str:
    return yaml.safe_load(cell.read_text())["arm"]["host"]


def test_the_robotiq_socket_and_the_cameras_of_an_emulated_cell(tmp_path: Path) -> None:
    cell = write_cell(
        tmp_path,
        cameras=[{"name": "front", "kind": "opencv", "width": 96, "height": 64, "fps": 15}],
    )
    data = yaml.safe_load(cell.read_text())
    data["cameras"][0]["source"] = f"http://{host_of(cell)}:8080/front"
    cell.write_text(yaml.safe_dump(data))
    with EmulatorProcess(cell):
        gripper = RobotiqGripper(host_of(cell))
        try:
            open_width = gripper.opening()
            gripper.command(1.0)
            time.sleep(1.0)
            assert gripper.opening() < 0.5 * open_width, "the gripper should close on command"
        finally:
            gripper.close()
        camera = OpenCVCamera("front", data["cameras"][0]["source"], 96, 64, 15)
        try:
            rig = CameraRig([camera])
            time.sleep(1.0)
            image = rig.images()["observation.images.front"]
            assert image.shape == (64, 96, 3) and image.std() > 5, "a rendered scene, not blank"
            assert 8 < camera.stats.fps < 25 and camera.stats.dropped == 0
        finally:
            camera.close()


def test_a_digital_output_gripper_through_ur_rtdes_io_interface(tmp_path: Path) -> None:
    import rtde_io

    cell = write_cell(tmp_path, gripper={"kind": "digital", "output": 2})
    with EmulatorProcess(cell):
        harness = HarnessClient(host_of(cell))
        io = rtde_io.RTDEIOInterface(host_of(cell))
        try:
            gripper = DigitalGripper(io, 2)
            opened = harness.reading()["gripper_opening"]
            gripper.command(1.0)
            time.sleep(0.8)
            assert harness.reading()["gripper_opening"] < 0.5 * opened
        finally:
            io.disconnect()
            harness.close()


@pytest.mark.parametrize(
    ("fault", "said"),
    [
        ("emergency_stop", "emergency stop is pressed"),
        ("local_mode", "left remote control"),
    ],
)
def test_each_stop_is_named_in_one_line_within_a_step(tmp_path: Path, fault: str, said: str):
    cell = write_cell(tmp_path)
    task = make_task("pick_place")
    with EmulatorProcess(cell):
        harness = HarnessClient(host_of(cell))
        robot = open_robot("real", task, cell=cell, emulated=True)
        try:
            robot.reset(task.sample_config(np.random.default_rng(0)))
            robot.act(np.zeros(7, np.float32))
            harness.fault(fault)
            with pytest.raises(RobotStopped, match=said) as stopped:
                for _ in range(2):  # the stop shows at the step it happens in, or the next
                    robot.act(np.zeros(7, np.float32))
            assert "\n" not in str(stopped.value)
        finally:
            robot.close()
            harness.close()


def test_a_lost_connection_is_named_in_one_line_and_acknowledging_reconnects(
    tmp_path: Path,
) -> None:
    """ur_rtde reconnects by itself after a lost connection and can crash doing so; it
    runs in a process of its own, so the host names the loss and, once acknowledged,
    connects afresh and goes on."""
    cell = write_cell(tmp_path)
    task = make_task("pick_place")
    config = task.sample_config(np.random.default_rng(0))
    with EmulatorProcess(cell):
        harness = HarnessClient(host_of(cell))
        robot = open_robot("real", task, cell=cell, emulated=True)
        try:
            robot.reset(config)
            robot.act(np.zeros(7, np.float32))
            harness.fault("drop_connection")
            with pytest.raises(RobotError, match="lost the connection to the controller") as lost:
                for _ in range(2):  # the loss shows at the step it happens in, or the next
                    robot.act(np.zeros(7, np.float32))
            assert "\n" not in str(lost.value)
            robot.unwrapped.acknowledge()
            robot.reset(config)
            before = harness.reading()["q"]
            for _ in range(5):
                robot.act(np.array([0.03, 0, 0, 0, 0, 0, 0], np.float32))
            assert np.abs(np.subtract(harness.reading()["q"], before)).max() > 1e-3
            assert harness.reading()["program_running"]
        finally:
            robot.close()
            harness.close()


def test_a_script_without_a_main_guard_opens_the_arm_once(tmp_path: Path) -> None:
    """ur_rtde's process is a fresh interpreter: the host's script is not run again in it."""
    cell = write_cell(tmp_path)
    script = tmp_path / "drive.py"
    script.write_text(
        "import sys, numpy as np\n"
        "from twinrl_robot.backends import open_robot\n"
        "from twinrl_sim.tasks import make_task\n"
        "task = make_task('pick_place')\n"
        "robot = open_robot('real', task, cell=sys.argv[1], emulated=True)\n"
        "robot.reset(task.sample_config(np.random.default_rng(0)))\n"
        "robot.act(np.zeros(7, np.float32))\n"
        "robot.close()\n"
        "print('drove the arm')\n"
    )
    with EmulatorProcess(cell):
        ran = subprocess.run(
            [sys.executable, str(script), str(cell)], capture_output=True, text=True, timeout=120
        )
    assert ran.returncode == 0, ran.stderr
    assert ran.stdout.count("drove the arm") == 1


def test_an_unreachable_controller_is_one_line(tmp_path: Path) -> None:
    cell = write_cell(tmp_path)  # nothing serves on its address
    with pytest.raises(RobotConnectionError, match="cannot reach the UR controller") as err:
        open_robot("real", make_task("pick_place"), cell=cell)
    assert "\n" not in str(err.value)
    result = twinrl_process("robot", "check", str(cell))
    assert result.returncode == 2
    assert "cannot reach the UR controller" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_a_taken_port_stops_a_second_emulator_with_one_line(tmp_path: Path) -> None:
    cell = write_cell(tmp_path)
    with (
        EmulatorProcess(cell),
        pytest.raises(RobotError, match="cannot serve the emulated RTDE port"),
        EmulatorProcess(cell),
    ):
        pass


def test_an_emulator_ends_with_the_process_that_started_it(tmp_path: Path) -> None:
    """A benchmark or test killed mid-run leaves no emulator holding the cell's ports."""
    cell = write_cell(tmp_path)
    starter = subprocess.Popen(
        [sys.executable, "-c", (
            "import sys, time\n"
            "from twinrl_robot.ur.emulator.harness import EmulatorProcess\n"
            f"with EmulatorProcess({str(cell)!r}) as emulator:\n"
            "    print(emulator.process.pid, flush=True)\n"
            "    time.sleep(600)\n"
        )],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        emulator = int(starter.stdout.readline())
    finally:
        starter.kill()  # no context exit, no clean-up: only the kernel knows
        starter.wait()
    deadline = time.monotonic() + 10.0
    while Path(f"/proc/{emulator}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    status = Path(f"/proc/{emulator}/status")
    gone = not status.exists() or "zombie" in status.read_text()
    assert gone, "the emulator outlived the process that started it"
    with EmulatorProcess(cell):  # and its ports are free again
        pass


def test_robot_check_reports_the_cell_and_records_the_safety_box(tmp_path: Path) -> None:
    cell = write_cell(tmp_path)
    with EmulatorProcess(cell):
        result = twinrl_process(
            "robot", "check", str(cell), "--seconds", "1", "--rerun", str(tmp_path / "c.rrd")
        )
    assert result.returncode == 0, result.stderr
    for line in ("PolyScope 5.15", "RUNNING", "servo loop", "500 Hz", "inside the safety"):
        assert line in result.stdout
    assert (tmp_path / "c.rrd").stat().st_size > 0


def test_a_camera_that_does_not_open_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="cannot be opened from source") as err:
        OpenCVCamera("front", str(tmp_path / "missing.mp4"), 64, 48, 30)
    assert "\n" not in str(err.value)


class _HeldCamera:
    """A camera whose frames the test hands over, to count stale ones exactly."""

    name, fps = "held", 10.0

    def __init__(self) -> None:
        self.stats = CameraStats()
        self.frame: Frame | None = None

    def deliver(self, index: int) -> None:
        self.frame = Frame(np.zeros((4, 4, 3), np.uint8), time.monotonic(), index)

    def latest(self) -> Frame | None:
        return self.frame

    def close(self) -> None:
        return None


def test_a_frame_seen_twice_is_counted_stale_never_silently_repeated() -> None:
    camera = _HeldCamera()
    rig = CameraRig([camera])
    camera.deliver(1)
    rig.images()
    rig.images()  # no new frame came: the step reuses frame 1
    camera.deliver(2)
    rig.images()
    assert rig.counts() == {"held": {"frames": 0, "dropped": 0, "stale": 1}}


def test_the_emulated_arm_protective_stops_when_a_link_hits_the_table() -> None:
    from twinrl_robot.ur.emulator.arm import EmulatedArm, SafetyMode

    arm = EmulatedArm(make_task("pick_place"), effects={})
    arm.program_running = True
    for _ in range(10):
        arm.tick()
    assert arm.safety_mode == SafetyMode.NORMAL, "the arm at home touches nothing"
    q = arm.cell.arm_q
    q[1] += 1.2  # the shoulder swings the arm down through the table
    arm.move(q, speed=2.0, acceleration=8.0)
    for _ in range(1500):
        arm.tick()
        if arm.safety_mode != SafetyMode.NORMAL:
            break
    assert arm.safety_mode == SafetyMode.PROTECTIVE_STOP and not arm.program_running
    held = arm.cell.arm_q
    arm.servo(held + 0.3)  # commands are refused until the stop is unlocked
    for _ in range(50):
        arm.tick()
    assert np.abs(arm.cell.arm_q - held).max() < 0.05


def test_an_episode_records_what_each_camera_delivered(tmp_path: Path) -> None:
    from twinrl_data.mcap_log import read_episode
    from twinrl_data.recorder import Recorder
    from twinrl_data.session import Session
    from twinrl_robot.loop import run_episode
    from twinrl_robot.scripted import ExpertSource

    cell = write_cell(tmp_path)
    data = yaml.safe_load(cell.read_text())
    url = f"http://{data['arm']['host']}:8080/front"
    data["cameras"] = [{"name": "front", "source": url, "width": 64, "height": 48, "fps": 15}]
    cell.write_text(yaml.safe_dump(data))
    task = make_task("pick_place")
    with EmulatorProcess(cell):
        robot = open_robot("real", task, cell=cell, emulated=True, cameras=("front",))
        recorder = Recorder(Session.create(tmp_path / "session"))
        config = task.sample_config(np.random.default_rng(0))
        meta = task.episode_meta(source="teleop", world="real", names=robot.names, config=config)
        source = ExpertSource(np.random.default_rng(0), np.random.default_rng(1), 0.0)
        try:
            result = run_episode(
                robot, source, task, config, judge=None, max_steps=8, recorder=recorder, meta=meta
            )
        finally:
            robot.close()
    saved = read_episode(result.path, images=True)
    counts = saved.meta.sensors["front"]
    assert counts["frames"] >= 8 and counts["dropped"] == 0
    assert counts["stale"] <= 1, "a 15 fps camera gives every 10 Hz step a new frame"
    assert saved.images["front"].shape == (8, 48, 64, 3)


def test_a_realsense_without_its_extra_says_how_to_install_it() -> None:
    from twinrl_robot.ur.cameras import RealSenseCamera

    try:
        import pyrealsense2  # noqa: F401
    except ImportError:
        with pytest.raises(CameraError, match=r"pip install 'twinrl\[realsense\]'"):
            RealSenseCamera("wrist", "123456789", 64, 48, 30)
    else:
        pytest.skip("pyrealsense2 is installed: the error path does not apply")


def test_a_command_the_emulator_does_not_run_is_said_not_silently_done(tmp_path: Path) -> None:
    import rtde_control
    import rtde_receive

    data = yaml.safe_load(write_cell(tmp_path).read_text())
    data["arm"]["tcp_offset"] = [0, 0, 0.1, 0, 0, 0]
    cell = tmp_path / "cell.yaml"
    cell.write_text(yaml.safe_dump(data))
    host = host_of(cell)
    with EmulatorProcess(cell) as emulator:
        receive = rtde_receive.RTDEReceiveInterface(host)
        control = rtde_control.RTDEControlInterface(host)
        try:
            control.setTcp([0, 0, 0.1, 0, 0, 0])
            tcp = np.array(receive.getActualTCPPose())
            control.getActualToolFlangePose()  # ur_rtde reads the answer a cycle late
            time.sleep(0.02)
            flange = np.array(control.getActualToolFlangePose())
            assert 0.099 < np.linalg.norm(tcp[:3] - flange[:3]) < 0.101
            control.zeroFtSensor()  # the emulated arm has no force-torque sensor
        finally:
            control.stopScript()
            control.disconnect()
            receive.disconnect()
        time.sleep(0.2)
        said = re.findall(r"ur_rtde command (\d+) is not emulated", emulator.errors())
        assert len(said) == 1
