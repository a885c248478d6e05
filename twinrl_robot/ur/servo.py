"""The servo stream: joint targets sent to a UR controller at its own rate.

The episode moves at the control rate (10 Hz); a UR controller servos at 125 Hz (CB3)
or 500 Hz (e-Series) and wants a servoJ target every one of its periods. The stream
runs in its own thread, paced by ur_rtde's ``initPeriod``/``waitPeriod``, and sends the
point of the current control step's segment that the clock has reached: each control
target's segment runs from the previous target to it over one control period, starting
when the previous segment ends (or now, if that has passed). So the arm follows the
same path whatever the host's timing jitter: a step that comes a little early waits for
the previous one to finish instead of cutting its corner. Every servoJ package
refreshes the controller's RTDE watchdog; a stream that stops (the host process hangs
or dies, the network goes) lets the watchdog stop the program on the controller.
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


class ServoStream:
    """Streams servo targets over ``control`` (an ``RTDEControlInterface``) at ``servo_hz``.

    Targets are joint positions; ``servo_pose`` (e.g. the controller TCP's forward
    kinematics) turns each into a TCP pose sent with servoL instead of servoJ. ``fault``
    is set, with a reason, when the controller refuses a target (its program stopped);
    the driver reports it at the next control step.
    """

    def __init__(
        self,
        control: object,
        servo_hz: float,
        servo_pose: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        self.control, self.servo_period = control, 1.0 / servo_hz
        self.servo_pose = servo_pose
        self.fault: str | None = None
        self.periods: list[float] = []  # s between consecutive targets sent (newest last)
        self._lock = threading.Lock()
        # (start, end, began, duration); the previous segment runs until this one begins.
        self._segment: tuple[np.ndarray, np.ndarray, float, float] | None = None
        self._previous: tuple[np.ndarray, np.ndarray, float, float] | None = None
        self._running = False
        self._thread: threading.Thread | None = None

    def start(self, q: np.ndarray) -> None:
        """Start streaming, holding ``q`` until the first target arrives."""
        self.stop()
        q = np.asarray(q, float)
        self._segment, self._previous = (q, q, time.monotonic(), 0.0), None
        self.fault = None
        self._running = True
        if sys.getswitchinterval() > GIL_SWITCH_INTERVAL:
            sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        self._thread = threading.Thread(target=self._run, name="ur-servo", daemon=True)
        self._thread.start()

    def push(self, target: np.ndarray, duration: float) -> None:
        """Move from the previous target to ``target`` over ``duration`` seconds, from the
        end of the previous segment (or now, when it has ended)."""
        now = time.monotonic()
        with self._lock:
            assert self._segment is not None, "start the stream first"
            _, end, began, length = self._segment
            if now < began:  # the previous push has not begun: it is replaced
                self._segment = (self._segment[0], np.asarray(target, float), began, duration)
                return
            self._previous = self._segment
            self._segment = (end, np.asarray(target, float), max(now, began + length), duration)

    def hold(self, q: np.ndarray) -> None:
        """Hold ``q`` (the arm stops where it is)."""
        q = np.asarray(q, float)
        with self._lock:
            self._segment, self._previous = (q, q, time.monotonic(), 0.0), None

    def stop(self) -> None:
        """Stop streaming (the thread ends; the controller holds the last target)."""
        self._running = False
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
        control, period = self.control, self.servo_period
        last = time.perf_counter()
        while self._running:
            began = control.initPeriod()  # type: ignore[attr-defined]
            with self._lock:
                q = self._point(time.monotonic())
            if self.servo_pose is None:
                sent = control.servoJ(  # type: ignore[attr-defined]
                    q.tolist(), 0.0, 0.0, period, SERVO_LOOKAHEAD, SERVO_GAIN
                )
            else:
                sent = control.servoL(  # type: ignore[attr-defined]
                    self.servo_pose(q).tolist(), 0.0, 0.0, period, SERVO_LOOKAHEAD, SERVO_GAIN
                )
            if not sent:
                self.fault = "the controller refused a servo target: its program is not running"
                self._running = False
                return
            now = time.perf_counter()
            self.periods.append(now - last)
            if len(self.periods) > 20_000:
                del self.periods[:10_000]
            last = now
            control.waitPeriod(began)  # type: ignore[attr-defined]
