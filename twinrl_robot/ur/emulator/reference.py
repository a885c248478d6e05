"""The controller's joint reference: servo targets, joint speeds, moves and stops turned
into one joint path, within the arm's speed and acceleration limits.

What a UR's trajectory generator does, one servo period at a time:

- **servoJ** (``q`` over ``t``): the path moves along the line from where it was when the
  target came to the target, reaching it ``t`` later, as ur_rtde's servo thread calling
  ``servoj(q, t)`` does; the newest target wins and, with none new, the path holds the last
  one. The reference runs at the stream's speed (from the previous target to the newest
  over ``t``, which no network jitter shifts) and closes on the path within
  :data:`SERVO_CORRECTION`, so a target a millisecond early or late does not kick the
  speed. servoj's ``lookahead_time`` and ``gain`` smooth the path first (a first-order
  filter, :func:`servo_smoothing`): on a steady stream the arm runs at the stream's speed,
  lagging it by that filter alone, more for a longer lookahead or a lower gain. When the
  stream stops, the arm brakes at its acceleration limit onto the last target.
- **speedJ**: each joint's speed approaches the commanded one at the given acceleration.
- **moveJ**: a synchronised trapezoidal joint move (the pendant's speed slider slows it).
- **stop**: the leading joint decelerates at the given rate, the others in proportion, so
  the arm comes to rest on the line it was moving along (``stopj``).
- **movel, speedl, stopl**: the tool's pose is planned in Cartesian space
  (:mod:`.tool_motion`) and the joints follow it through the inverse kinematics, each
  period from where they are.

Every joint-space command keeps each joint's speed within :attr:`JointLimits.speed` and
its acceleration within :attr:`JointLimits.acceleration`: a command that asks for more
is followed as fast as the arm can (a controller limits the motion). A tool-space motion
is not slowed for its joints: one that asks too much of them (near a singularity) trips
the arm's speed check, as a UR's movel does. Positions are checked by the arm, which
raises the protective stop a UR does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from twinrl_robot.ur.emulator.tool_motion import (
    LinearMove,
    ToolMotion,
    ToolSpeed,
    ToolStop,
    displacement,
)

SERVO_CORRECTION = 0.02  # s: time constant with which the reference closes on the path
SERVO_GRACE = 0.004  # s: a target this late still finds the stream's speed unchanged
SERVO_LOOKAHEAD, SERVO_GAIN = 0.1, 300.0  # servoj's defaults
SERVO_SMOOTHING = 0.02  # the smoothing time constant per second of lookahead, at gain 300


def servo_smoothing(lookahead: float, gain: float) -> float:
    """The time constant (s) of the first-order filter that smooths a servo path:
    ``SERVO_SMOOTHING * lookahead * 300 / gain``.

    A UR's servoj follows its target with a proportional ``gain`` and projects the
    position ``lookahead`` s ahead with the current speed (the URScript manual: a low
    lookahead reacts fast, a high one prevents overshoot; a high gain reacts faster).
    Its filter is not published; one first-order lag that grows with the lookahead and
    shrinks with the gain keeps both trends. At the defaults (0.1 s, 300) it is 2 ms, so
    a default stream tracks, and echoes its targets, as it did before these parameters
    were modelled; at 0.2 s and gain 100 it is 12 ms, at 0.03 s and 2000 under 0.1 ms.
    The factor is a choice, not a measurement of a UR.
    """
    return SERVO_SMOOTHING * lookahead * SERVO_GAIN / max(gain, 1.0)


class ToolKinematics(Protocol):
    """The controller's TCP: its pose for joint positions, and the inverse kinematics."""

    def pose(self, q: np.ndarray) -> np.ndarray: ...

    def solve(self, pose: np.ndarray, q_start: np.ndarray) -> np.ndarray: ...


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
    smoothing: float  # s: the filter's time constant (servo_smoothing)

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


@dataclass
class _Tool:
    motion: ToolMotion


class JointReference:
    """The joint reference ``q`` (rad), its speed ``qd`` and acceleration ``qdd``,
    advanced one ``period`` (s) at a time by :meth:`advance`."""

    def __init__(
        self, q: np.ndarray, limits: JointLimits, period: float, tool: ToolKinematics
    ) -> None:
        self.q = np.asarray(q, float).copy()
        self.qd = np.zeros_like(self.q)
        self.qdd = np.zeros_like(self.q)
        self.limits, self.period, self.tool = limits, period, tool
        self._motion: _Servo | _Speed | _Move | _Stop | _Tool | None = None
        self._smoothed = (self.q.copy(), self.qd.copy())  # the servo path and its speed

    @property
    def idle(self) -> bool:
        """Whether nothing is commanded (a servo stream counts until stopped)."""
        return self._motion is None

    @property
    def servo_target(self) -> np.ndarray | None:
        """The newest servo target, while servoing."""
        return self._motion.target.copy() if isinstance(self._motion, _Servo) else None

    # -------------------------------------------------------------- commands
    def servo(
        self,
        target: np.ndarray,
        duration: float,
        age: float = 0.0,
        lookahead: float = SERVO_LOOKAHEAD,
        gain: float = SERVO_GAIN,
    ) -> None:
        """servoJ: reach ``target`` ``duration`` s after it came, ``age`` s ago, the path
        smoothed as ``lookahead`` (s) and ``gain`` say (:func:`servo_smoothing`)."""
        motion = self._motion
        target = np.asarray(target, float).copy()
        duration = max(duration, self.period)
        if isinstance(motion, _Servo):
            start, previous = motion.point(motion.elapsed - age), motion.target
        else:
            start = previous = self.q
            self._smoothed = (self.q.copy(), self.qd.copy())
        velocity = (target - previous) / duration
        smoothing = servo_smoothing(lookahead, gain)
        self._motion = _Servo(start, target, velocity, duration, age, smoothing)

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

    def move_linear(self, goal: np.ndarray, speed: float, acceleration: float) -> None:
        """movel: the TCP to pose ``goal`` along a line, at ``speed`` (m/s) and
        ``acceleration`` (m/s^2)."""
        start = self.tool.pose(self.q)
        self._motion = _Tool(LinearMove(start, goal, speed, acceleration))

    def speed_tool(self, twist: np.ndarray, acceleration: float) -> None:
        """speedl: run the tool at ``twist`` (m/s, rad/s), reached at ``acceleration``
        (m/s^2), from the twist it has now."""
        self._motion = _Tool(
            ToolSpeed(self.tool.pose(self.q), self.tool_twist(), twist, acceleration)
        )

    def stop_tool(self, deceleration: float) -> None:
        """stopl: bring the tool to rest on its current line at ``deceleration``
        (m/s^2, and rad/s^2 for its turning)."""
        self._motion = _Tool(ToolStop(self.tool.pose(self.q), self.tool_twist(), deceleration))

    def tool_twist(self) -> np.ndarray:
        """The TCP's twist (m/s, rad/s; base frame) as the joint reference moves now."""
        previous = self.tool.pose(self.q - self.qd * self.period)
        return displacement(previous, self.tool.pose(self.q)) / self.period

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
            self._follow(*self._smooth(motion))
            motion.elapsed += dt
        elif isinstance(motion, _Tool):
            pose = motion.motion.step(dt, speed_fraction)
            if pose is None:
                self._set(self.q)
                self._motion = None
            else:
                self._set(self.tool.solve(pose, self.q))
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

    def _smooth(self, motion: _Servo) -> tuple[np.ndarray, np.ndarray]:
        """The servo path's point and speed now, through the lookahead's first-order
        filter (which starts where the reference was when the stream began)."""
        point, feed_forward = motion.point(motion.elapsed), motion.feed_forward(motion.elapsed)
        weight = 1.0 - np.exp(-self.period / max(motion.smoothing, 1e-6))
        position, speed = self._smoothed
        self._smoothed = (
            position + (point - position) * weight,
            speed + (feed_forward - speed) * weight,
        )
        return self._smoothed

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
