"""ur_rtde's own client against the emulator, call by call, as on a UR controller
(issue 51): servoJ streams report smooth joint speeds, a watchdog kick never swallows a
servo target, the joints keep within a UR5e's speed and acceleration limits, a target
beyond the joint range is a protective stop seen through RTDE and the dashboard, and a
stream that goes silent is stopped under control soon after the watchdog trips."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.robot.test_ur_cell import EMULATED, write_cell
from twinrl_robot.ur.emulator.harness import EmulatorProcess

pytestmark = EMULATED

WRIST = 5  # the joint the streams turn (wrist 3)
RATE = 125.0  # Hz of the streams, as a CB3 client or a cautious e-Series one sends
SPEED_LIMIT = np.pi  # rad/s: a UR5e's joints
ACCELERATION_LIMIT = 40.0  # rad/s^2: ur_rtde's own bound on joint accelerations
PROTECTIVE_STOP, NORMAL = 3, 1


@pytest.fixture(scope="module")
def host(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    cell = write_cell(tmp_path_factory.mktemp("cell"))
    with EmulatorProcess(cell):
        yield yaml.safe_load(Path(cell).read_text())["arm"]["host"]


@pytest.fixture
def ur(host: str) -> Iterator[tuple]:
    """A fresh control script and a receiver; the arm is left unlocked and at rest."""
    import dashboard_client
    import rtde_control
    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(host)
    control = rtde_control.RTDEControlInterface(host, RATE)
    try:
        yield control, receive
    finally:
        if receive.getSafetyMode() != NORMAL:
            dashboard = dashboard_client.DashboardClient(host)
            dashboard.connect()
            dashboard.unlockProtectiveStop()
            dashboard.disconnect()
        if control.isProgramRunning():
            control.stopScript()
        control.disconnect()
        receive.disconnect()
        time.sleep(0.2)  # at rest for the next test


@dataclass
class Samples:
    """What the receiver read once per stream period (controller time, joints)."""

    timestamp: np.ndarray  # s
    q: np.ndarray  # (n, 6) rad
    qd: np.ndarray  # (n, 6) rad/s
    running: np.ndarray  # (n,) the control program's state

    def distinct(self) -> Samples:
        """One sample per controller package (the client may read one twice)."""
        keep = np.concatenate([[True], np.diff(self.timestamp) > 0])
        return Samples(self.timestamp[keep], self.q[keep], self.qd[keep], self.running[keep])


def record(receive, samples: list) -> None:
    """Read one package's values: a read that a newer package cut through is retried."""
    while True:
        stamp = receive.getTimestamp()
        sample = (stamp, receive.getActualQ(), receive.getActualQd(), receive.getRuntimeState())
        if receive.getTimestamp() == stamp:
            samples.append((*sample[:3], sample[3] == 2))
            return


def collected(samples: list) -> Samples:
    stamps, q, qd, running = zip(*samples, strict=True)
    return Samples(np.array(stamps), np.array(q), np.array(qd), np.array(running))


def stream_servoj(control, receive, seconds: float, *, speed: float, kick: bool) -> Samples:
    """servoJ(q, 0, 0, 1/RATE, 0.1, 300) turning the wrist at ``speed`` (rad/s) for
    ``seconds``, kicking the watchdog after every target when ``kick``."""
    start = np.array(receive.getActualQ())
    samples: list = []
    period = 1.0 / RATE
    for i in range(round(seconds * RATE)):
        began = control.initPeriod()
        q = start.copy()
        q[WRIST] += speed * i * period
        assert control.servoJ(q.tolist(), 0.0, 0.0, period, 0.1, 300)
        if kick:
            assert control.kickWatchdog()
        record(receive, samples)
        control.waitPeriod(began)
    return collected(samples)


def steady_speeds(samples: Samples, skip: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """The wrist's reported speed, averaged over each interval between two controller
    packages (a host that catches up after a late period changes the speed within one),
    and the finite difference of its reported positions over the same interval, after
    the first ``skip`` seconds."""
    s = samples.distinct()
    keep = (s.timestamp >= s.timestamp[0] + skip)[1:]
    speed = (s.qd[1:, WRIST] + s.qd[:-1, WRIST]) / 2.0
    difference = np.diff(s.q[:, WRIST]) / np.diff(s.timestamp)
    return speed[keep], difference[keep]


def test_a_servoj_stream_reports_the_smooth_speed_its_positions_move_at(ur) -> None:
    """A UR5e's reported speed changes by a median 1e-4 rad/s between 8 ms samples and
    matches the positions' finite difference within 0.005 rad/s RMS; the tolerances
    leave room for a loaded host's jitter, and stepped targets (0.2 to 0.8 rad/s from
    one period to the next) fail them by tens of times."""
    control, receive = ur
    qd, difference = steady_speeds(stream_servoj(control, receive, 1.5, speed=1.0, kick=False))
    assert np.median(np.abs(np.diff(qd))) < 0.01
    mismatch = np.abs(qd - difference)
    assert np.sqrt(np.mean(mismatch**2)) < 0.02, np.sort(mismatch)[-5:]
    assert np.median(qd) == pytest.approx(1.0, abs=0.02)


def test_a_watchdog_kick_after_every_servoj_never_swallows_a_target(ur) -> None:
    """ur_rtde sends a kick as command 0 right behind the servoJ package; the target
    must still count, so the wrist moves every period (a loaded host may delay a few
    packages, but swallowed targets stalled it for tens of periods) and within a UR5e's
    top speed."""
    control, receive = ur
    control.setWatchdog(50.0)
    samples = stream_servoj(control, receive, 1.5, speed=1.0, kick=True)
    qd, difference = steady_speeds(samples)
    assert np.abs(samples.qd).max() < SPEED_LIMIT
    assert np.mean(np.abs(difference - 1.0) > 0.25) < 0.05, "the wrist stalled and jumped"
    assert np.median(np.abs(np.diff(qd))) < 0.01
    assert samples.running.all()


def test_a_servo_target_far_off_is_reached_within_the_speed_and_acceleration_limits(
    ur,
) -> None:
    control, receive = ur
    start = np.array(receive.getActualQ())
    goal = start.copy()
    goal[WRIST] += 1.0
    samples: list = []
    for _ in range(round(0.8 * RATE)):
        began = control.initPeriod()
        assert control.servoJ(goal.tolist(), 0.0, 0.0, 1.0 / RATE, 0.1, 300)
        record(receive, samples)
        control.waitPeriod(began)
    s = collected(samples).distinct()
    assert np.abs(s.qd).max() < SPEED_LIMIT * 1.05
    acceleration = np.abs(np.diff(s.qd[:, WRIST]) / np.diff(s.timestamp))
    assert acceleration.max() < ACCELERATION_LIMIT * 1.5
    assert s.q[-1, WRIST] == pytest.approx(goal[WRIST], abs=2e-3)
    assert receive.getSafetyMode() == NORMAL


def test_a_speedj_stream_with_kicks_runs_at_its_speed_and_speed_stop_rests_the_arm(
    ur,
) -> None:
    control, receive = ur
    # A blocking stop sends nothing while the arm brakes (200 ms here): on a controller
    # too, the watchdog must outlast it.
    control.setWatchdog(4.0)
    speeds = np.zeros(6)
    speeds[WRIST] = -0.8
    samples: list = []
    for _ in range(round(0.8 * RATE)):
        began = control.initPeriod()
        assert control.speedJ(speeds.tolist(), 4.0, 1.0 / RATE)
        assert control.kickWatchdog()
        record(receive, samples)
        control.waitPeriod(began)
    s = collected(samples).distinct()
    assert s.qd[-20:, WRIST] == pytest.approx(-0.8, abs=0.01)
    assert control.speedStop(4.0)
    assert wait_for(lambda: np.abs(receive.getActualQd()).max() < 0.02, 0.1)
    assert control.isProgramRunning()


def test_a_speedj_beyond_the_top_speed_runs_at_the_top_speed(ur) -> None:
    control, receive = ur
    speeds = np.zeros(6)
    speeds[WRIST] = 5.0
    samples: list = []
    for _ in range(round(0.4 * RATE)):
        began = control.initPeriod()
        assert control.speedJ(speeds.tolist(), 20.0, 1.0 / RATE)
        record(receive, samples)
        control.waitPeriod(began)
    assert control.speedStop(20.0)
    s = collected(samples).distinct()
    assert s.qd[-5:, WRIST] == pytest.approx(SPEED_LIMIT, abs=0.02)
    assert receive.getSafetyMode() == NORMAL


def test_movej_blocking_arrives_and_an_asynchronous_one_reports_progress_and_stops(ur) -> None:
    control, receive = ur
    start = np.array(receive.getActualQ())
    goal = start + np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.3])
    assert control.moveJ(goal.tolist(), 1.0, 2.0)
    assert np.array(receive.getActualQ()) == pytest.approx(goal, abs=2e-3)
    assert control.moveJ(start.tolist(), 0.5, 1.0, True)
    time.sleep(0.3)
    assert np.abs(receive.getActualQd()).max() > 0.1, "the asynchronous move did not start"
    assert control.getAsyncOperationProgress() >= 0, "it is under way"
    control.stopJ(2.0)
    assert wait_for(lambda: np.abs(receive.getActualQd()).max() < 0.02, 0.1)
    assert wait_for(lambda: control.getAsyncOperationProgress() < 0, 0.1)
    stopped = np.array(receive.getActualQ())
    assert 0.05 < np.abs(stopped - start).max() < 0.25, "it should stop short of the goal"
    assert control.moveJ(start.tolist(), 1.0, 2.0, True)
    assert control.getAsyncOperationProgress() >= 0
    assert wait_for(lambda: control.getAsyncOperationProgress() < 0, 2.0)
    assert np.array(receive.getActualQ()) == pytest.approx(start, abs=2e-3)


def test_servo_stop_brings_a_stream_to_rest_without_swinging_past_its_target(ur) -> None:
    """servoStop(a) brakes from the arm's speed; from the per-period target jumps of old,
    it overshot by up to 0.8 rad."""
    control, receive = ur
    samples = stream_servoj(control, receive, 0.5, speed=1.0, kick=False)
    last = samples.q[0, WRIST] + 1.0 * (round(0.5 * RATE) - 1) / RATE
    assert control.servoStop(10.0)
    assert wait_for(lambda: np.abs(receive.getActualQd()).max() < 0.02, 0.1)
    # Braking at 10 rad/s^2 from 1 rad/s takes 0.05 rad, from wherever the stop came.
    assert receive.getActualQ()[WRIST] < last + 0.07


def test_a_target_beyond_the_joint_limits_is_a_protective_stop(ur, host: str) -> None:
    import dashboard_client

    control, receive = ur
    start = np.array(receive.getActualQ())
    beyond = start.copy()
    beyond[2] = 3.3  # the elbow turns +-180 deg
    assert control.servoJ(beyond.tolist(), 0.0, 0.0, 1.0 / RATE, 0.1, 300)
    time.sleep(0.2)
    assert receive.getSafetyMode() == PROTECTIVE_STOP
    assert receive.isProtectiveStopped()
    assert not control.isProgramRunning()
    assert np.array(receive.getActualQ()) == pytest.approx(start, abs=2e-3)
    dashboard = dashboard_client.DashboardClient(host)
    dashboard.connect()
    try:
        assert "PROTECTIVE_STOP" in dashboard.safetystatus()
        assert not control.servoJ(start.tolist(), 0.0, 0.0, 1.0 / RATE, 0.1, 300)
        dashboard.unlockProtectiveStop()
        assert wait_for(lambda: receive.getSafetyMode() == NORMAL)
        assert control.reuploadScript()
        assert wait_for(control.isProgramRunning)
        assert not control.moveJ(beyond.tolist(), 1.0, 2.0), "moveJ must fail, not clamp"
        assert wait_for(lambda: receive.getSafetyMode() == PROTECTIVE_STOP)
    finally:
        dashboard.disconnect()


def wait_for(condition: Callable[[], bool], seconds: float = 1.0) -> bool:
    """Whether ``condition`` holds within ``seconds`` (RTDE reports at its own rate)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return False


def test_a_silent_stream_is_at_rest_within_100_ms_of_the_watchdog_tripping(ur) -> None:
    """A servoJ stream that feeds the 50 Hz watchdog goes silent at 1 rad/s: the script's
    servo thread brings the wrist onto its last target, the watchdog stops the program,
    and the arm rests within 100 ms of that, decelerating within the arm's limit."""
    control, receive = ur
    control.setWatchdog(50.0)
    stream_servoj(control, receive, 0.6, speed=1.0, kick=False)
    samples: list = []
    deadline = time.monotonic() + 0.4
    while time.monotonic() < deadline:
        record(receive, samples)
        time.sleep(0.001)
    s = collected(samples).distinct()
    assert not s.running[-1], "the watchdog should stop the program"
    tripped = s.timestamp[np.argmin(s.running)]
    moving = np.abs(s.qd).max(axis=1) >= 0.02
    rested = s.timestamp[np.flatnonzero(moving)[-1] + 1]
    assert rested - tripped <= 0.1, f"at rest {(rested - tripped) * 1000:.0f} ms after the trip"
    deceleration = np.abs(np.diff(s.qd[:, WRIST]) / np.diff(s.timestamp))
    assert deceleration.max() < ACCELERATION_LIMIT * 1.5
