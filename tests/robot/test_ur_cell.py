"""The UR driver against the emulator, through the real ur_rtde: it connects and moves,
the scripted expert solves pick_place through it, a logged episode replays, the watchdog
stops a frozen host's arm within 100 ms, and stops end an episode saved as aborted."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.robot.test_loop import Scripted
from tests.robot.test_realtime import needs_realtime, thread_policy
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import Recorder
from twinrl_data.session import Session
from twinrl_robot.backends import open_robot
from twinrl_robot.cell_file import load_cell
from twinrl_robot.loop import privileged_success, run_episode
from twinrl_robot.replay_source import ReplaySource
from twinrl_robot.scripted import ExpertSource
from twinrl_robot.ur.driver import RobotStopped
from twinrl_robot.ur.emulator import free_loopback_host
from twinrl_robot.ur.emulator.arm import STOP_TIME
from twinrl_robot.ur.emulator.harness import EmulatorProcess, HarnessClient
from twinrl_robot.wrappers.base import layers
from twinrl_sim.tasks import make_task

AT_REST = 0.02  # rad/s
# Tests against the emulator: Linux routes all of 127.0.0.0/8 to loopback (each
# emulated controller has an address of its own), and the emulator keeps the
# controller's clock, so these do not run beside other tests.
EMULATED = [
    pytest.mark.skipif(sys.platform != "linux", reason="loopback 127.0.0.N"),
    pytest.mark.realtime,
]
pytestmark = EMULATED


def write_cell(folder: Path, **changes: object) -> Path:
    """A cell file for an emulator on a free loopback address."""
    cell = {
        "name": "emulated",
        "twin": "pick_place",
        "arm": {"model": "ur5e", "host": free_loopback_host(), "control_hz": 10},
        "gripper": {"kind": "robotiq_2f85"},
        # The scripted expert plans its strides ahead (up to 5 cm per step) and assumes
        # they are executed; a person would adapt to a tighter per-step limit, it does not.
        "safety": {"max_step_translation": 0.05},
        **changes,
    }
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(cell))
    return path


@pytest.fixture
def emulated(tmp_path: Path) -> Iterator[tuple[Path, EmulatorProcess]]:
    cell = write_cell(tmp_path)
    with EmulatorProcess(cell, effects=None) as emulator:
        yield cell, emulator


def test_the_real_ur_rtde_connects_and_drives_the_emulator(emulated) -> None:
    import rtde_control
    import rtde_receive

    cell, emulator = emulated
    host = yaml.safe_load(cell.read_text())["arm"]["host"]
    receive = rtde_receive.RTDEReceiveInterface(host)
    control = rtde_control.RTDEControlInterface(host)  # checks remote control off 127.0.0.1
    try:
        assert control.isProgramRunning() and receive.getRobotMode() == 7
        start = np.array(receive.getActualQ())
        goal = start + np.array([0.1, -0.05, 0.05, 0.0, 0.0, 0.1])
        assert control.moveJ(goal.tolist(), 1.0, 2.0)
        assert np.abs(np.array(receive.getActualQ()) - goal).max() < 2e-3
        for i in range(100):  # 0.2 s of servoJ at 500 Hz
            began = control.initPeriod()
            control.servoJ((goal + 0.001 * i).tolist(), 0.0, 0.0, 0.002, 0.1, 300)
            control.waitPeriod(began)
        time.sleep(0.1)
        assert np.abs(np.array(receive.getActualQ()) - (goal + 0.099)).max() < 5e-3
        assert control.servoStop()
    finally:
        control.stopScript()
        control.disconnect()
        receive.disconnect()
    assert "not URSim" in emulator.banner


def test_the_expert_solves_pick_place_through_the_driver_and_its_episode_replays(
    emulated, tmp_path: Path
) -> None:
    cell, _ = emulated
    task = make_task("pick_place")
    robot = open_robot("real", task, cell=cell, emulated=True, effort=True)
    session = Session.create(tmp_path / "session")
    recorder = Recorder(session)
    config = task.sample_config(np.random.default_rng(3), "ID")
    try:
        source = ExpertSource(np.random.default_rng(0), np.random.default_rng(1), 0.0)
        meta = task.episode_meta(
            source="teleop", world="real", names=robot.names, config=config, region="ID"
        )
        first = run_episode(
            robot,
            source,
            task,
            config,
            judge=privileged_success(robot),
            recorder=recorder,
            meta=meta,
        )
        assert first.success, f"the expert failed through the driver after {first.steps} steps"
        logged = read_episode(first.path, images=False)
        replay_meta = task.episode_meta(
            source="replay", world="real", names=robot.names, config=config, region="ID"
        )
        second = run_episode(
            robot,
            ReplaySource(logged),
            task,
            config,
            judge=None,
            max_steps=len(logged.data["action"]),
            recorder=recorder,
            meta=replay_meta,
        )
    finally:
        robot.close()
    replayed = read_episode(second.path, images=False)
    q_logged = logged.data["observation.state"][:, :6]
    q_replayed = replayed.data["observation.state"][:, :6]
    rms = path_distance_rms(q_logged, q_replayed)
    # A loaded host shifts when targets land by a period now and then (about a milliradian
    # of path); a replay that does not retrace the log is off by tens.
    assert rms < 3e-3, f"the replay retraced the joint path within {rms * 1000:.2f} mrad RMS"
    assert logged.meta.world == "real" and "observation.effort" in logged.data
    assert logged.data["observation.wrench"].shape == (len(q_logged), 6)


def path_distance_rms(path: np.ndarray, other: np.ndarray, reach: int = 3) -> float:
    """RMS distance (rad) from each point of ``path`` to ``other``'s polyline near the
    same step: how far apart the two joint paths run, whatever the phase at which each
    control step happened to sample them (a few ms of host jitter is a mrad at speed)."""
    distances = []
    for i, point in enumerate(path):
        nearest = np.inf
        for j in range(max(0, i - reach), min(len(other) - 1, i + reach)):
            start, segment = other[j], other[j + 1] - other[j]
            length = float(segment @ segment)
            t = 0.0 if length == 0 else float(np.clip((point - start) @ segment / length, 0, 1))
            nearest = min(nearest, float(np.linalg.norm(point - start - t * segment)))
        distances.append(nearest)
    return float(np.sqrt(np.mean(np.square(distances)) / path.shape[1]))


def test_a_host_busy_between_episodes_keeps_the_control_program(emulated) -> None:
    """Connecting arms the 100 ms watchdog; the host then opens its recorder, arranges a
    scene or writes an episode for longer than that without servoing, and the program
    must still be running when the next episode starts."""
    cell, _ = emulated
    host = yaml.safe_load(cell.read_text())["arm"]["host"]
    harness = HarnessClient(host)
    task = make_task("pick_place")
    robot = open_robot("real", task, cell=cell, emulated=True)
    try:
        time.sleep(0.5)  # five watchdog periods with nothing from the episode loop
        assert harness.reading()["program_running"], "the watchdog stopped an idle host"
        config = task.sample_config(np.random.default_rng(0))
        robot.reset(config)
        robot.act(np.array([0.01, 0, 0, 0, 0, 0, 0], np.float32))
        robot.unwrapped.hold()
        time.sleep(0.5)  # between episodes
        robot.reset(config)
    finally:
        robot.close()
        harness.close()


def test_a_frozen_host_lets_the_watchdog_stop_the_arm(emulated) -> None:
    """The host freezes mid-motion: its controller link stops streaming, and the arm is at
    rest no later than a UR's watchdog would have it, the cell's watchdog_ms (100) and a
    controlled stop (STOP_TIME); the watchdog ends the program and the host, resumed, is
    told so. The arm usually rests sooner (the stream's end brakes it onto its last
    target: 76-122 ms measured), by how late a loaded host's link saw the freeze."""
    cell, _ = emulated
    host = yaml.safe_load(cell.read_text())["arm"]["host"]
    driver = subprocess.Popen(
        [sys.executable, "-c", _STREAMING_HOST, str(cell)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    harness = HarnessClient(host)
    try:
        assert driver.stdout is not None
        assert driver.stdout.readline().strip() == "moving", "the host never started moving"
        time.sleep(0.5)
        moving = harness.reading()
        assert np.abs(moving["qd"]).max() > 0.05, "the arm should move while the host streams"
        driver.send_signal(signal.SIGSTOP)  # the host process hangs
        frozen_at = harness.reading()["timestamp"]
        while True:
            reading = harness.reading()
            # At rest: under 0.02 rad/s (about 1 deg/s) on every joint; the servo's settling
            # below that moves the tool by less than a millimetre.
            if np.abs(reading["qd"]).max() < AT_REST:
                break
            assert reading["timestamp"] - frozen_at < 1.0, "the arm never stopped"
        # The controller's stamps are multiples of its period; their difference is
        # compared in whole microseconds, not to the last bit of a float.
        stopped_after = round(reading["timestamp"] - frozen_at, 6)
        bound = load_cell(cell).safety.watchdog_ms / 1e3
        assert stopped_after <= bound + STOP_TIME, f"the arm took {stopped_after * 1e3:.0f} ms"
        time.sleep(0.2)
        assert not harness.reading()["program_running"], "the watchdog should end the program"
        driver.send_signal(signal.SIGCONT)  # the host comes back and is told, in one line
        printed, _ = driver.communicate(timeout=30)
        said = [line for line in printed.splitlines() if line.startswith("stopped: ")]
        assert said and "watchdog" in said[0], printed
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        harness.close()


_STREAMING_HOST = """
import sys, numpy as np
from twinrl_robot.backends import open_robot
from twinrl_robot.cell_file import load_cell
from twinrl_robot.errors import RobotError
from twinrl_sim.tasks import make_task
task = make_task("pick_place")
robot = open_robot("real", task, cell=sys.argv[1], emulated=True)
robot.reset(task.sample_config(np.random.default_rng(0)))
print("moving", flush=True)
try:
    while True:
        for sign in (1, -1):
            for _ in range(10):
                robot.act(np.array([0, sign * 0.03, 0, 0, 0, 0, 0], np.float32))
except RobotError as stop:
    print("stopped:", stop, flush=True)
robot.close()
"""


def test_a_protective_stop_aborts_the_episode_keeps_its_data_and_blocks_until_acknowledged(
    emulated, tmp_path: Path
) -> None:
    cell, _ = emulated
    host = yaml.safe_load(cell.read_text())["arm"]["host"]
    harness = HarnessClient(host)
    task = make_task("pick_place")
    robot = open_robot("real", task, cell=cell, emulated=True)
    recorder = Recorder(Session.create(tmp_path / "session"))
    config = task.sample_config(np.random.default_rng(0), "ID")
    meta = task.episode_meta(source="teleop", world="real", names=robot.names, config=config)

    class StoppedMidway(ExpertSource):
        steps = 0

        def act(self, observation):
            StoppedMidway.steps += 1
            if StoppedMidway.steps == 6:
                harness.fault("protective_stop")  # the arm hits something
            return super().act(observation)

    source = StoppedMidway(np.random.default_rng(0), np.random.default_rng(1), 0.0)
    try:
        with pytest.raises(RobotStopped, match="protective stop") as stopped:
            run_episode(robot, source, task, config, judge=None, recorder=recorder, meta=meta)
        assert "\n" not in str(stopped.value)
        assert StoppedMidway.steps == 6, "the stop must be seen within one control step"
        saved = read_episode(session_file(tmp_path), images=False)
        assert saved.meta.aborted and "protective stop" in saved.meta.aborted
        # The five steps completed before the stop are kept; the sixth was cut short by it.
        assert len(saved.data["action"]) == 5 and saved.meta.success is False
        with pytest.raises(RobotStopped, match="protective stop"):
            robot.act(np.zeros(7, np.float32))  # nothing is sent until acknowledged
        import dashboard_client

        dashboard = dashboard_client.DashboardClient(host)
        dashboard.connect()
        dashboard.unlockProtectiveStop()
        dashboard.disconnect()
        robot.unwrapped.acknowledge()
        robot.reset(config)
        robot.act(np.array([0.01, 0, 0, 0, 0, 0, 0], np.float32))
    finally:
        robot.close()
        harness.close()


def test_a_slow_move_to_the_start_pose_is_waited_for_and_a_halted_one_is_stopped(
    emulated,
) -> None:
    """The pendant's speed slider at 20 % makes the move to the start pose five times
    slower and it completes; at 0 % the arm halts short of it, which ends the reset
    with one line within a few seconds, without a protective stop."""
    cell, _ = emulated
    harness = HarnessClient(yaml.safe_load(cell.read_text())["arm"]["host"])
    task = make_task("pick_place")
    robot = open_robot("real", task, cell=cell, emulated=True)
    configs = [task.sample_config(np.random.default_rng(seed), "OOD") for seed in (0, 1)]
    try:
        robot.reset(configs[0])
        harness.fault("speed_slider_20")
        robot.unwrapped.start_q = robot.unwrapped.start_q + np.array([0.3, 0, 0, 0, 0, 0])
        start = time.monotonic()
        robot.reset(configs[1])  # 0.3 rad at a fifth of the reset speed: about 3 s
        assert time.monotonic() - start > 2.5
        assert np.abs(robot.unwrapped.measured_q() - robot.unwrapped.start_q).max() < 2e-3
        harness.fault("speed_slider_0")
        robot.unwrapped.start_q = robot.unwrapped.start_q - np.array([0.3, 0, 0, 0, 0, 0])
        start = time.monotonic()
        with pytest.raises(
            RobotStopped, match=r"stopped (29|30)\d\.\d mrad short of the start"
        ) as err:
            robot.reset(configs[1])
        assert time.monotonic() - start < 5.0 and "\n" not in str(err.value)
        assert harness.reading()["safety_mode"] == 1  # normal: no stop was needed
    finally:
        harness.fault("speed_slider_100")
        robot.close()
        harness.close()


def session_file(folder: Path) -> Path:
    (episode,) = sorted((folder / "session").rglob("*.mcap"))
    return episode


def test_servol_streams_the_tcp_pose_and_the_controller_solves_the_ik(tmp_path: Path) -> None:
    cell = write_cell(
        tmp_path,
        arm={
            "model": "ur5e",
            "host": free_loopback_host(),
            "servo": "servol",
            "tcp_offset": [0, 0, 0.15, 0, 0, 0],
        },
    )
    task = make_task("pick_place")
    with EmulatorProcess(cell):
        robot = open_robot("real", task, cell=cell, emulated=True)
        try:
            robot.reset(task.sample_config(np.random.default_rng(0)))
            start = robot.observe()["observation.state"][12:15]
            for _ in range(10):
                sent = robot.act(np.array([0.01, 0.0, -0.005, 0, 0, 0, 0], np.float32))
            time.sleep(0.2)
            state = robot.observe()["observation.state"]
            assert np.allclose(state[12:15] - start, [0.1, 0.0, -0.05], atol=5e-3)
            assert np.abs(state[:6] - sent.joint_target).max() < 5e-3
        finally:
            robot.close()


@needs_realtime
def test_a_cell_with_a_priority_runs_its_loop_at_it_on_the_emulated_arm(tmp_path: Path) -> None:
    arm = {"model": "ur5e", "host": free_loopback_host(), "realtime_priority": 20}
    cell = write_cell(tmp_path, arm=arm)
    task = make_task("pick_place")
    config = task.sample_config(np.random.default_rng(0), "ID")
    seen = []
    with EmulatorProcess(cell):
        robot = open_robot("real", task, cell=cell, emulated=True)
        try:
            *_, backend = layers(robot)
            link = backend._link.pid
            run_episode(
                robot, Scripted([np.zeros(7, np.float32)] * 5), task, config, judge=None,
                max_steps=5, on_step=lambda t, sent: seen.append(thread_policy()),
            )  # fmt: skip
            threads = Path(f"/proc/{link}/task").iterdir()
            link_policies = {thread_policy(int(thread.name)) for thread in threads}
        finally:
            robot.close()
    assert seen == [os.SCHED_FIFO] * 5 and thread_policy() == os.SCHED_OTHER
    # ur_rtde's threads and the servo stream's keep the normal policy (see realtime.py).
    assert link_policies == {os.SCHED_OTHER}
