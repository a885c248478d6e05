"""The servo stream against a recording stand-in for ur_rtde's control interface: it
kicks the watchdog whenever it is not servoing, sends nothing after a fault, and never
lets two threads' commands interleave."""

from __future__ import annotations

import threading
import time

import numpy as np

from twinrl_robot.ur.servo import ServoStream, SharedControl


class RecordingControl:
    """Answers like ``RTDEControlInterface`` and records each command; a command that
    overlaps another (two threads inside at once) is counted."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.overlaps = 0
        self.program_running = True
        self._inside = 0
        self._guard = threading.Lock()

    def _command(self, name: str, seconds: float = 0.0) -> bool:
        with self._guard:
            self._inside += 1
            self.overlaps += self._inside > 1
        time.sleep(seconds)
        self.calls.append(name)
        with self._guard:
            self._inside -= 1
        return self.program_running

    def kickWatchdog(self) -> bool:
        return self._command("kick")

    def servoJ(self, *args: object) -> bool:
        return self._command("servoJ")

    def moveJ(self, *args: object) -> bool:
        return self._command("moveJ", 0.01)


def wait_for(condition, seconds: float = 2.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_the_watchdog_is_kicked_from_open_whenever_no_target_is_sent() -> None:
    control = RecordingControl()
    stream = ServoStream(SharedControl(control), 500.0)
    stream.open()
    try:
        wait_for(lambda: control.calls.count("kick") >= 5)
        stream.start(np.zeros(6))
        wait_for(lambda: control.calls.count("servoJ") >= 5)
        stream.stop()
        kicks = control.calls.count("kick")
        wait_for(lambda: control.calls.count("kick") >= kicks + 5)
        assert stream.fault is None
    finally:
        stream.close()
    count = len(control.calls)
    time.sleep(0.02)
    assert len(control.calls) == count, "a closed stream sends nothing"


def test_a_refused_kick_is_a_fault_and_silences_the_stream_until_resumed() -> None:
    control = RecordingControl()
    stream = ServoStream(SharedControl(control), 500.0)
    stream.open()
    try:
        control.program_running = False  # the watchdog or the pendant stopped the program
        wait_for(lambda: stream.fault is not None)
        assert "refused a watchdog kick" in stream.fault
        count = len(control.calls)
        time.sleep(0.02)
        assert len(control.calls) == count, "nothing is sent after a fault"
        control.program_running = True
        stream.resume()
        wait_for(lambda: len(control.calls) > count + 3)
        assert stream.fault is None
    finally:
        stream.close()


def test_the_drivers_commands_never_interleave_with_the_streams() -> None:
    control = RecordingControl()
    shared = SharedControl(control)
    stream = ServoStream(shared, 500.0)
    stream.open()
    try:
        for _ in range(20):
            shared.moveJ([0.0] * 6, 0.6, 1.2, True)
        stream.start(np.zeros(6))
        for _ in range(20):
            shared.moveJ([0.0] * 6, 0.6, 1.2, True)
    finally:
        stream.close()
    assert control.calls.count("moveJ") == 40
    assert control.overlaps == 0


class LateControl(RecordingControl):
    """Records each servoJ target; one period overruns by 30 ms, as a thread starved by a
    loaded host does."""

    def __init__(self) -> None:
        super().__init__()
        self.targets: list[np.ndarray] = []
        self.sent_at: list[float] = []
        self.stall_after: int | None = None

    def servoJ(self, q: list[float], *args: object) -> bool:
        self.targets.append(np.array(q))
        self.sent_at.append(time.monotonic())
        if len(self.targets) == self.stall_after:
            time.sleep(0.03)
        return self._command("servoJ")


def _streamed_through_a_stall(max_speed: float | None) -> LateControl:
    """What the controller got while a 0.5 rad/s path was streamed through a 30 ms
    stall."""
    control = LateControl()
    stream = ServoStream(SharedControl(control), 500.0, max_speed=max_speed)
    stream.open()
    try:
        stream.start(np.zeros(6))
        wait_for(lambda: len(control.targets) >= 3)
        control.stall_after = len(control.targets) + 5
        stream.push(np.full(6, 0.1), 0.2, time.monotonic() + 0.2)  # 0.5 rad/s
        wait_for(lambda: len(control.targets) > control.stall_after + 40)
    finally:
        stream.close()
    return control


def _largest_step(max_speed: float | None) -> float:
    """The largest change between consecutive targets through the stall."""
    control = _streamed_through_a_stall(max_speed)
    return float(np.abs(np.diff(np.stack(control.targets), axis=0)).max())


def test_a_target_goes_every_servo_period_and_a_stall_is_not_made_up_in_a_burst() -> None:
    control = _streamed_through_a_stall(None)
    gaps = np.diff(control.sent_at) * 1000.0  # ms
    stall = control.stall_after
    assert stall is not None and gaps[stall - 1] >= 30.0
    assert 1.8 < np.median(gaps) < 2.5  # on schedule, 500 Hz
    # The periods the stall took are not sent back to back afterwards.
    assert np.median(gaps[stall : stall + 10]) > 1.5


def test_a_late_servo_period_is_caught_up_at_the_speed_limit_not_in_a_jump() -> None:
    # Without a limit the 30 ms the thread missed come as one target: 0.015 rad in one
    # 2 ms period, 7.5 rad/s.
    assert _largest_step(None) > 0.012
    # With one, every target is at most 1 rad/s x 2 ms from the last.
    assert _largest_step(1.0) <= 0.002 + 1e-12
