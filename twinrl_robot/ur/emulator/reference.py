"""The controller's joint reference: servo targets, joint speeds, moves and stops turned
into one joint path, within the arm's speed and acceleration limits.

What a UR's trajectory generator does, one servo period at a time:

- **servoJ** (``q`` over ``t``): the path moves along the line from where it was when the
  target came to the target, reaching it ``t`` later, as ur_rtde's servo thread calling
  ``servoj(q, t)`` does; the newest target wins and, with none new, the path holds the last
  one. The reference runs at the stream's speed (from the previous target to the newest
  over ``t``, which no network jitter shifts) and closes on the path within
  :data:`SERVO_CORRECTION`: no lag on a steady stream, and a target a millisecond early
  or late does not kick the speed. When the stream stops, the arm brakes at its
  acceleration limit onto the last target.
- **speedJ**: each joint's speed approaches the commanded one at the given acceleration.
- **moveJ**: a synchronised trapezoidal joint move (the pendant's speed slider slows it).
- **stop**: the leading joint decelerates at the given rate, the others in proportion, so
  the arm comes to rest on the line it was moving along (``stopj``).

Every joint's speed is held within :attr:`JointLimits.speed` and its acceleration within
:attr:`JointLimits.acceleration`: a command that asks for more is followed as fast as
the arm can (a controller limits the motion). Positions are checked by the arm, which
raises the protective stop a UR does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SERVO_CORRECTION = 0.02  # s: time constant with which the reference closes on the path
SERVO_GRACE = 0.004  # s: a target this late still finds the stream's speed unchanged


@dataclass(frozen=True)
class JointLimits:
    """The arm's joint range (rad), its joints' top speed (rad/s) and acceleration
    (rad/s^2)."""

    lower: np.ndarray
    upper: np.ndarray
    speed: float
    acceleration: float

    def beyond(self, q: np.ndarray) -> list[int]:
        """The joints of ``q`` outside the range."""
        outside = (q < self.lower) | (q > self.upper)
        return [int(i) for i in np.flatnonzero(outside)]


@dataclass
class _Servo:
    start: np.ndarray  # the path where the target came
    target: np.ndarray
    velocity: np.ndarray  # rad/s the stream moves at: from the previous target to this one
    duration: float  # s the path takes to reach the target
    elapsed: float  # s since the target came

    def point(self, elapsed: float) -> np.ndarray:
        fraction = min(1.0, max(0.0, elapsed / self.duration))
        return self.start + (self.target - self.start) * fraction

    def feed_forward(self, elapsed: float) -> np.ndarray:
        if elapsed >= self.duration + SERVO_GRACE:
            return np.zeros_like(self.target)
        return self.velocity


@dataclass
class _Speed:
    velocity: np.ndarray
    acceleration: float


@dataclass
class _Move:
    target: np.ndarray
    speed: float
    acceleration: float


@dataclass
class _Stop:
    deceleration: float


class JointReference:
    """The joint reference ``q`` (rad), its speed ``qd`` and acceleration ``qdd``,
    advanced one ``period`` (s) at a time by :meth:`advance`."""

    def __init__(self, q: np.ndarray, limits: JointLimits, period: float) -> None:
        self.q = np.asarray(q, float).copy()
        self.qd = np.zeros_like(self.q)
        self.qdd = np.zeros_like(self.q)
        self.limits, self.period = limits, period
        self._motion: _Servo | _Speed | _Move | _Stop | None = None

    @property
    def idle(self) -> bool:
        """Whether nothing is commanded (a servo stream counts until stopped)."""
        return self._motion is None

    @property
    def servo_target(self) -> np.ndarray | None:
        """The newest servo target, while servoing."""
        return self._motion.target.copy() if isinstance(self._motion, _Servo) else None

    # -------------------------------------------------------------- commands
    def servo(self, target: np.ndarray, duration: float, age: float = 0.0) -> None:
        """servoJ: reach ``target`` ``duration`` s after it came, ``age`` s ago."""
        motion = self._motion
        target = np.asarray(target, float).copy()
        duration = max(duration, self.period)
        if isinstance(motion, _Servo):
            start, previous = motion.point(motion.elapsed - age), motion.target
        else:
            start = previous = self.q
        self._motion = _Servo(start, target, (target - previous) / duration, duration, age)

    def speed(self, velocity: np.ndarray, acceleration: float) -> None:
        """speedJ: run the joints at ``velocity`` (rad/s), reached at ``acceleration``."""
        self._motion = _Speed(np.asarray(velocity, float).copy(), acceleration)

    def move(self, target: np.ndarray, speed: float, acceleration: float) -> None:
        """moveJ: go to ``target`` at ``speed`` (rad/s) and ``acceleration`` (rad/s^2)."""
        self._motion = _Move(np.asarray(target, float).copy(), speed, acceleration)

    def stop(self, deceleration: float) -> None:
        """Bring the joints to rest on their current line at ``deceleration`` (rad/s^2,
        of the leading joint)."""
        self._motion = _Stop(max(deceleration, 1e-3))

    def hold(self, q: np.ndarray) -> None:
        """Stand still at ``q`` from now on (a halted arm)."""
        self.q = np.asarray(q, float).copy()
        self.qd[:] = 0.0
        self.qdd[:] = 0.0
        self._motion = None

    # ------------------------------------------------------------------ tick
    def advance(self, speed_fraction: float = 1.0) -> None:
        """One servo period of the current command."""
        motion, dt = self._motion, self.period
        if isinstance(motion, _Servo):  # the path as the newest target left it, now
            self._follow(motion.point(motion.elapsed), motion.feed_forward(motion.elapsed))
            motion.elapsed += dt
        elif isinstance(motion, _Speed):
            limit = min(motion.acceleration, self.limits.acceleration)
            self._accelerate(np.clip((motion.velocity - self.qd) / dt, -limit, limit))
        elif isinstance(motion, _Move):
            self._move_step(motion, speed_fraction)
        elif isinstance(motion, _Stop):
            self._stop_step(motion)
        else:
            self.qd[:] = 0.0
            self.qdd[:] = 0.0

    def _follow(self, point: np.ndarray, feed_forward: np.ndarray) -> None:
        """Track the servo path: the stream's speed plus a correction of the distance to
        the path that brakes in time at the acceleration limit, so a stream that stops
        comes to rest on its last target without swinging past it again."""
        error = point - self.q
        correction = np.minimum(
            np.abs(error) / SERVO_CORRECTION,
            np.sqrt(2.0 * self.limits.acceleration * np.abs(error)),
        )
        self._accelerate((feed_forward + np.sign(error) * correction - self.qd) / self.period)

    def _accelerate(self, acceleration: np.ndarray) -> None:
        """Integrate one period of ``acceleration`` within the limits."""
        limits, dt = self.limits, self.period
        qd = np.clip(
            self.qd + np.clip(acceleration, -limits.acceleration, limits.acceleration) * dt,
            -limits.speed,
            limits.speed,
        )
        self.qdd = (qd - self.qd) / dt
        self.q = self.q + qd * dt
        self.qd = qd

    def _move_step(self, motion: _Move, fraction: float) -> None:
        """One period of a synchronised trapezoidal joint move toward ``motion.target``."""
        remaining = motion.target - self.q
        distance = float(np.max(np.abs(remaining)))
        if distance < 1e-6:
            self._set(motion.target)
            self._motion = None
            return
        # The speed slider slows the move's time: speeds by it, accelerations by its square.
        if fraction <= 0.0:
            self._set(self.q)
            return
        dt = self.period
        acceleration = min(motion.acceleration, self.limits.acceleration) * fraction**2
        top = min(motion.speed, self.limits.speed) * fraction
        current = float(np.max(np.abs(self.qd)))
        braking = np.sqrt(2.0 * acceleration * distance)
        speed = min(top, current + acceleration * dt, braking)
        step = min(distance, max(speed, acceleration * dt) * dt)
        self._set(self.q + remaining * (step / distance))

    def _stop_step(self, motion: _Stop) -> None:
        lead = float(np.max(np.abs(self.qd)))
        slower = max(0.0, lead - motion.deceleration * self.period)
        self._set(self.q + self.qd * (slower / lead if lead > 0 else 0.0) * self.period)
        if slower == 0.0:
            self._motion = None

    def _set(self, q: np.ndarray) -> None:
        """Move the reference to ``q`` this period (its speed follows)."""
        qd = (q - self.q) / self.period
        self.qdd = (qd - self.qd) / self.period
        self.q, self.qd = np.asarray(q, float).copy(), qd
