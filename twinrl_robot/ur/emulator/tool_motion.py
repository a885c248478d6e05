"""The controller's tool-space motions: the TCP pose, one servo period at a time, of
``movel``, ``speedl`` and ``stopl`` as a UR plans them, in Cartesian space (the joints
follow through the inverse kinematics, see :class:`.reference.JointReference`).

- **movel** (``movel(pose, a, v)``): the TCP runs along the straight line to the goal
  with a trapezoidal speed profile, its orientation turning about one fixed axis in step.
  ``v`` and ``a`` bound the tool's linear speed (m/s) and acceleration (m/s^2), and its
  turning speed in rad/s and rad/s^2 (what a UR does for a move that only turns): the
  profile runs over the longer of the two, so neither exceeds its bound.
- **speedl** (``speedl(xd, a)``): the tool's twist approaches the commanded one along a
  straight line in twist space, at ``a`` m/s^2 (and rad/s^2 for the turning part, as
  URScript does when no ``aRot`` is given).
- **stopl** (``stopl(a)``): the twist the tool had shrinks to zero at ``a`` m/s^2 (and
  rad/s^2), its direction kept, so the tool comes to rest on the line it moved along
  after ``speed / a`` seconds.

Poses are ``[x, y, z, rx, ry, rz]`` (m, axis-angle rad) and twists ``[vx, vy, vz, wx,
wy, wz]`` (m/s, rad/s), both in the robot's base frame, as URScript takes them.
"""

from __future__ import annotations

import numpy as np

from twinrl_sim.control import quat_conj, quat_mul, quat_to_rotvec, rotvec_to_quat

ARRIVED = 1e-9  # m (or rad) of a move's length left that counts as there


def displacement(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """The translation and the (base-frame) rotation vector from pose ``start`` to
    ``end``: ``compose(start, displacement(start, end)) == end``."""
    turn = quat_mul(rotvec_to_quat(end[3:]), quat_conj(rotvec_to_quat(start[3:])))
    return np.concatenate([end[:3] - start[:3], quat_to_rotvec(turn)])


def compose(pose: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``pose`` moved by the translation ``step[:3]`` and turned by the base-frame
    rotation vector ``step[3:]``."""
    turned = quat_mul(rotvec_to_quat(step[3:]), rotvec_to_quat(pose[3:]))
    return np.concatenate([pose[:3] + step[:3], quat_to_rotvec(turned)])


def _larger_part(vector: np.ndarray) -> float:
    """The larger of the linear and the angular part's norm (the one a bound binds)."""
    return max(float(np.linalg.norm(vector[:3])), float(np.linalg.norm(vector[3:])))


class LinearMove:
    """movel from ``start`` to ``goal`` at ``speed`` and ``acceleration`` (see the module
    docstring)."""

    def __init__(
        self, start: np.ndarray, goal: np.ndarray, speed: float, acceleration: float
    ) -> None:
        self.start = np.asarray(start, float).copy()
        self.delta = displacement(self.start, np.asarray(goal, float))
        self.length = _larger_part(self.delta)
        self.speed, self.acceleration = speed, acceleration
        self.travelled = 0.0
        self.rate = 0.0  # length per second

    @property
    def twist(self) -> np.ndarray:
        """The tool's twist now."""
        return self.delta / self.length * self.rate if self.length > 0 else np.zeros(6)

    def step(self, dt: float, fraction: float = 1.0) -> np.ndarray | None:
        """The pose after one period ``dt``, or ``None`` once arrived. The pendant's speed
        slider ``fraction`` slows the move's time: speeds by it, accelerations by its
        square."""
        remaining = self.length - self.travelled
        if remaining <= ARRIVED:
            return None
        if fraction > 0.0:
            acceleration = self.acceleration * fraction**2
            top = self.speed * fraction
            rate = min(top, self.rate + acceleration * dt, np.sqrt(2.0 * acceleration * remaining))
            advance = min(remaining, max(rate, acceleration * dt) * dt)
        else:
            advance = 0.0
        self.travelled += advance
        self.rate = advance / dt
        return compose(self.start, self.delta * (self.travelled / self.length))


class ToolSpeed:
    """speedl: from ``pose`` moving at ``twist``, approach ``target`` at
    ``acceleration`` and run on at it until stopped or replaced."""

    def __init__(
        self, pose: np.ndarray, twist: np.ndarray, target: np.ndarray, acceleration: float
    ) -> None:
        self.pose = np.asarray(pose, float).copy()
        self.twist = np.asarray(twist, float).copy()
        self.target = np.asarray(target, float).copy()
        self.acceleration = acceleration

    def step(self, dt: float, fraction: float = 1.0) -> np.ndarray:
        """The pose after one period ``dt`` (a tool speed ignores the speed slider here)."""
        change = self.target - self.twist
        needed = _larger_part(change)
        if needed > 0.0:
            self.twist = self.twist + change * min(1.0, self.acceleration * dt / needed)
        self.pose = compose(self.pose, self.twist * dt)
        return self.pose


class ToolStop:
    """stopl: from ``pose`` moving at ``twist``, come to rest at ``deceleration``."""

    def __init__(self, pose: np.ndarray, twist: np.ndarray, deceleration: float) -> None:
        self.pose = np.asarray(pose, float).copy()
        self.initial = np.asarray(twist, float).copy()
        self.duration = _larger_part(self.initial) / max(deceleration, 1e-3)
        self.elapsed = 0.0

    @property
    def twist(self) -> np.ndarray:
        if self.duration <= 0.0:
            return np.zeros(6)
        return self.initial * max(0.0, 1.0 - self.elapsed / self.duration)

    def step(self, dt: float, fraction: float = 1.0) -> np.ndarray | None:
        """The pose after one period ``dt``, or ``None`` once at rest."""
        if self.elapsed >= self.duration:
            return None
        t0, t1 = self.elapsed, min(self.elapsed + dt, self.duration)
        # The twist falls linearly: integrate it exactly over the period.
        share = (t1 - t0) - (t1**2 - t0**2) / (2.0 * self.duration)
        self.pose = compose(self.pose, self.initial * share)
        self.elapsed = t0 + dt
        return self.pose


ToolMotion = LinearMove | ToolSpeed | ToolStop
