"""The servo stream: the one thread that talks to a UR controller at its own rate.

The episode moves at the control rate (10 Hz); a UR controller servos at 125 Hz (CB3)
or 500 Hz (e-Series) and wants a servoJ target every one of its periods. The stream
runs in its own thread, paced by the host's clock, and sends the
point of the current control step's segment that the clock has reached: each control
target's segment runs from the previous target to it and ends with the step's control
period, when the next observation is taken (as the twin's servos reach each target by
the end of their period); it starts when the previous segment ends, or, for a step the
host was late with, as soon as it comes, running faster to end on time. So the arm
follows the same path whatever the host's timing jitter, and one late step does not
leave it behind the control loop for the rest of the episode.

The thread sleeps until each period is due, one servo period after the last (a thread
late by a whole period starts over from now), not in ur_rtde's ``waitPeriod``, which
spins through the last part of every period. Against the emulator on an idle 2-core
host that spin kept the stream's process at a quarter of a core and its targets came
every 2.54 ms on average (p50 2.17 ms) where the controller servos every 2; sleeping,
it takes 17 % of a core and sends every 2.10 ms (p50 2.007 ms).

A servo target is reached one servo period after it is sent, so the thread itself
being late (a loaded host: 10-30 ms between targets were measured with a busy core)
would turn the path it missed into one target's jump, which the controller runs at
many times the path's speed (the emulated arm hit its speed limit and pressed the
table with 570 N). Each target therefore moves at most ``max_speed`` times the servo
period from the one sent before: after a late period the arm catches up with the path
at that speed instead of jumping.

The controller's RTDE watchdog stops its program when no command came for the cell's
``watchdog_ms``. Every servoJ package refreshes it; between episodes (the arm moving to
its start pose, objects being arranged, the host writing an episode) the thread kicks
it instead, from the moment the connection opens until it closes. So only a host that
hangs or dies, or a network that goes, lets the watchdog stop the program; after a
fault the thread sends nothing until the stop is acknowledged.

ur_rtde's control interface speaks a command-register protocol in which one command
must finish before the next begins, so the driver and this thread share it through
:class:`SharedControl`, one command at a time.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable

import numpy as np

SERVO_LOOKAHEAD = 0.1  # s: servoJ's lookahead time (0.03..0.2); smooths the target
SERVO_GAIN = 300.0  # servoJ's proportional gain (100..2000)
GIL_SWITCH_INTERVAL = 2e-4  # s: how soon the stream thread gets the interpreter back
MIN_SEGMENT = 0.5  # of a control period: the fastest a segment may run to catch up
STOP_WAIT = 0.5  # s: the longest stop() waits for a target in flight
IDLE, SERVO, SILENT, CLOSED = "idle", "servo", "silent", "closed"


class SharedControl:
    """An ``RTDEControlInterface`` used from several threads, one command at a time.

    Every method call on it holds one lock.
    """

    def __init__(self, control: object) -> None:
        self._control = control
        self._lock = threading.Lock()

    def __getattr__(self, name: str) -> Callable:
        """Looked up once per name: the wrapper is kept, so the servo thread's calls at
        the controller's rate cost no more than a plain attribute."""
        method = getattr(self._control, name)
        if not callable(method):
            return method

        def call(*args: object) -> object:
            with self._lock:
                return method(*args)

        setattr(self, name, call)
        return call


class ServoStream:
    """Streams servo targets over ``control`` at ``servo_hz``, and keeps the watchdog
    fed between episodes.

    Targets are joint positions, each at most ``max_speed`` (rad/s) times the servo
    period from the one sent before; ``servo_pose`` (e.g. the controller TCP's forward
    kinematics) turns each into a TCP pose sent with servoL instead of servoJ. ``fault``
    is set, with a reason, when the controller refuses a command (its program stopped)
    or the connection fails, or when ``host_alive`` says the host has stopped (the stream
    then runs in a process of its own); the thread then falls silent, the
    watchdog stops the controller's program, and the driver reports the fault at the
    next control step.
    """

    def __init__(
        self,
        control: SharedControl,
        servo_hz: float,
        servo_pose: Callable[[np.ndarray], np.ndarray] | None = None,
        host_alive: Callable[[], bool] | None = None,
        max_speed: float | None = None,
    ) -> None:
        self.control, self.servo_period = control, 1.0 / servo_hz
        self.servo_pose, self.host_alive = servo_pose, host_alive
        # rad a joint's target may move from one servo period to the next (None: any)
        self.max_step = None if max_speed is None else max_speed * self.servo_period
        self._sent: np.ndarray | None = None  # the last target sent while servoing
        self.fault: str | None = None
        self.connection_failed = False  # the fault is the connection's, not a refusal
        self.periods: list[float] = []  # s between consecutive targets sent (newest last)
        self._lock = threading.Lock()
        # (start, end, began, duration); the previous segment runs until this one begins.
        self._segment: tuple[np.ndarray, np.ndarray, float, float] | None = None
        self._previous: tuple[np.ndarray, np.ndarray, float, float] | None = None
        self._mode = SILENT
        self._thread: threading.Thread | None = None
        self._periods_run = 0  # the thread's periods so far (stop waits for one to pass)

    def open(self) -> None:
        """Start the thread, kicking the watchdog (call once, right after connecting)."""
        self._mode = IDLE
        if sys.getswitchinterval() > GIL_SWITCH_INTERVAL:
            sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        self._thread = threading.Thread(target=self._run, name="ur-servo", daemon=True)
        self._thread.start()

    def start(self, q: np.ndarray) -> None:
        """Start streaming, holding ``q`` until the first target arrives."""
        q = np.asarray(q, float)
        with self._lock:
            self._segment, self._previous = (q, q, time.monotonic(), 0.0), None
            self._sent = None
        self.fault = None
        self._mode = SERVO

    def push(self, target: np.ndarray, duration: float, until: float) -> None:
        """Move from the previous target to ``target``, from the end of the previous
        segment (or now, when it has ended) until ``until`` (monotonic seconds), never
        faster than over MIN_SEGMENT of the control period ``duration``."""
        now = time.monotonic()
        with self._lock:
            assert self._segment is not None, "start the stream first"
            _, end, began, length = self._segment
            if now < began:  # the previous push has not begun: it is replaced
                self._segment = (self._segment[0], np.asarray(target, float), began, duration)
                return
            start = max(began + length, now)
            length = max(until - start, MIN_SEGMENT * duration)
            self._previous = self._segment
            self._segment = (end, np.asarray(target, float), start, length)

    def hold(self, q: np.ndarray) -> None:
        """Hold ``q`` (the arm stops where it is)."""
        q = np.asarray(q, float)
        with self._lock:
            self._segment, self._previous = (q, q, time.monotonic(), 0.0), None

    def stop(self) -> None:
        """Stop sending targets (the controller holds the last one); the watchdog is
        still kicked, so the driver may move the arm with other commands. Returns once
        no target is in flight: a servoJ the thread was about to send would otherwise
        reach the controller after the driver's next move and cancel it, as a UR's
        control script does (the arm then stopped short of the start pose)."""
        if self._mode != SERVO:
            return
        self._mode = IDLE
        seen, deadline = self._periods_run, time.monotonic() + STOP_WAIT
        running = self._thread is not None and self._thread is not threading.current_thread()
        while running and self._periods_run < seen + 2 and time.monotonic() < deadline:
            time.sleep(self.servo_period / 2)

    def resume(self) -> None:
        """After an acknowledged fault: kick the watchdog again."""
        self.fault, self.connection_failed = None, False
        if self._mode == SILENT:
            self._mode = IDLE

    def silence(self) -> None:
        """Send nothing more (a fault): the controller's program stays stopped."""
        if self._mode != CLOSED:
            self._mode = SILENT

    def close(self) -> None:
        """End the thread."""
        self._mode = CLOSED
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None

    def _point(self, now: float) -> np.ndarray:
        assert self._segment is not None
        segment = self._segment
        if now < segment[2] and self._previous is not None:
            segment = self._previous
        start, end, began, duration = segment
        if duration <= 0.0:
            return end.copy()
        fraction = min(1.0, max(0.0, (now - began) / duration))
        return start + (end - start) * fraction

    def _run(self) -> None:
        control = self.control
        last: float | None = None
        due = time.monotonic()  # when the current period began, on schedule
        while (mode := self._mode) != CLOSED:
            if mode == SILENT:
                last = None
            elif self.host_alive is not None and not self.host_alive():
                self._fail(
                    "the host process was stopped (Ctrl-Z, a signal or a debugger), so the "
                    "arm was left to the controller's watchdog; acknowledge to go on"
                )
                continue
            else:
                try:
                    sent = self._send_target() if mode == SERVO else control.kickWatchdog()
                except RuntimeError as err:  # ur_rtde lost the connection
                    self.connection_failed = True
                    self._fail(f"the connection to the controller failed ({err})")
                    continue
                if not sent:
                    what = "a servo target" if mode == SERVO else "a watchdog kick"
                    self._fail(f"the controller refused {what}: its program is not running")
                    continue
                last = self._count_period(last) if mode == SERVO else None
            self._periods_run += 1
            due = self._wait(due)

    def _wait(self, due: float) -> float:
        """Sleep until the next period, one servo period after ``due``; returns when it
        is due. A thread late by a whole period starts over from now (no burst)."""
        due += self.servo_period
        now = time.monotonic()
        if due < now - self.servo_period:
            due = now
        time.sleep(max(0.0, due - now))
        return due

    def _send_target(self) -> bool:
        with self._lock:
            q = self._point(time.monotonic())
            if self._sent is not None and self.max_step is not None:
                q = self._sent + np.clip(q - self._sent, -self.max_step, self.max_step)
            self._sent = q
        period = self.servo_period
        if self.servo_pose is None:
            return self.control.servoJ(q.tolist(), 0.0, 0.0, period, SERVO_LOOKAHEAD, SERVO_GAIN)
        pose = self.servo_pose(q).tolist()
        return self.control.servoL(pose, 0.0, 0.0, period, SERVO_LOOKAHEAD, SERVO_GAIN)

    def _fail(self, reason: str) -> None:
        if self._mode != CLOSED:
            self.fault = reason
            self._mode = SILENT

    def _count_period(self, last: float | None) -> float:
        now = time.perf_counter()
        if last is not None:
            self.periods.append(now - last)
            if len(self.periods) > 20_000:
                del self.periods[:10_000]
        return now
