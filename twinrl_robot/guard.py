"""The joint-level safety guard every joint target passes before it reaches a real arm.

Whatever chose the target (a policy through the IK, a person at a teleop device, a
logged episode being replayed, an excitation trajectory), the guard makes it one the
cell's limits allow: joint positions kept ``joint_margin`` from the limits, joint speed
and acceleration bounded over the control period, the tool centre point kept inside the
workspace box with the tool axis inside the cone around straight down, and every corner of
the tool (:mod:`twinrl_robot.tool_clearance`) a clearance above the table, which it nears
no faster than an approach speed (a servo overshoots by more the faster it arrives, and a
finger that strikes the table stops the arm for its force limit). Targets are
clipped, never refused, and the guard brakes ahead of a boundary: a target is accepted
only if the arm could still stop from it, braking at the acceleration limit, without
crossing a limit. Between full braking (safe by induction) and the requested motion, a
bisection picks the motion nearest the request that keeps that promise, so speed and
acceleration limits hold even while it stops the arm at the box's wall. A *start* pose
outside the limits is refused (:meth:`JointGuard.check_start`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_robot.errors import RobotError

Kinematics = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""Joint positions (rad) -> TCP position (m) and quaternion (wxyz) in the base frame."""

BOX_TOLERANCE = 1e-3  # m a target's TCP may stand outside the box (IK rounding)
BISECTIONS = 12


class UnsafeStart(RobotError):
    """A start pose (a reset, a replay's first target) lies outside the safety limits."""


@dataclass(frozen=True)
class GuardLimits:
    """The numbers the guard keeps (base frame, SI units)."""

    q_low: np.ndarray  # rad, the joints' limits with the margin taken off
    q_high: np.ndarray
    max_speed: float  # rad/s per joint
    max_acceleration: float  # rad/s^2 per joint
    box_low: np.ndarray  # m
    box_high: np.ndarray
    cone_deg: float  # tool axis within this angle of straight down
    tool_points: np.ndarray  # (n, 3) m, TCP frame: what of the tool must stay off the table
    table_top: float  # m
    table_clearance: float  # m every tool point keeps above the table
    approach_height: float  # m above the clearance within which the tool's lowest point
    approach_speed: float  # descends no faster than this (m/s)


@dataclass(frozen=True)
class Guarded:
    """A guarded target and what was clipped to make it safe (empty: nothing)."""

    q: np.ndarray
    clipped: tuple[str, ...]


class JointGuard:
    """Keeps a stream of joint targets inside ``limits`` (see the module docstring).

    ``period`` is the time between targets (the control period); ``kinematics`` the
    twin's forward kinematics, the same the IK inverts.
    """

    def __init__(self, limits: GuardLimits, kinematics: Kinematics, period: float) -> None:
        self.limits, self.kinematics, self.period = limits, kinematics, period
        self._last: np.ndarray | None = None
        self._velocity: np.ndarray | None = None
        self._height = np.inf  # of the tool's lowest point above the table at _last

    def reset(self, q: np.ndarray) -> None:
        """Start guarding from the arm at rest at ``q`` (which must be a safe start)."""
        self.check_start(q)
        self.anchor(q)

    def anchor(self, q: np.ndarray) -> None:
        """Go on from the arm held at ``q`` (an operator took over): the next targets
        start there at rest. Unchecked: the arm already stands there."""
        self._last = np.asarray(q, float).copy()
        self._velocity = np.zeros_like(self._last)
        self._height = self._inspect(self._last)[1]

    def check_start(self, q: np.ndarray, what: str = "the start pose") -> None:
        """Refuse (:class:`UnsafeStart`) a pose outside the joint limits, box or cone."""
        problem = self.violation(np.asarray(q, float))
        if problem:
            raise UnsafeStart(
                f"{what} is outside the cell's safety limits ({problem}); move the arm "
                "inside them by hand or widen the cell file's `safety` section"
            )

    def violation(self, q: np.ndarray) -> str:
        """What ``q`` breaks (joint limits, box, cone, the table's clearance), or ``""``
        when it is safe."""
        return self._inspect(q)[0]

    def _inspect(self, q: np.ndarray) -> tuple[str, float]:
        """What ``q`` breaks (``""``: nothing), and how high the tool's lowest point
        stands above the table there (m; NaN when a joint is beyond its limit)."""
        lim = self.limits
        below = np.flatnonzero(q < lim.q_low - 1e-9)
        above = np.flatnonzero(q > lim.q_high + 1e-9)
        if below.size or above.size:
            joints = ", ".join(str(int(j) + 1) for j in np.concatenate([below, above]))
            return f"joint {joints} beyond its limit and margin", np.nan
        position, quat = self.kinematics(q)
        rotation = np.empty(9)
        mujoco.mju_quat2Mat(rotation, quat)
        height = position[2] + float((lim.tool_points @ rotation[6:]).min()) - lim.table_top
        outside = (position < lim.box_low - BOX_TOLERANCE) | (
            position > lim.box_high + BOX_TOLERANCE
        )
        if outside.any():
            axes = "".join("xyz"[i] for i in np.flatnonzero(outside))
            where = np.round(position, 3).tolist()
            return f"tool centre point {where} m outside the box in {axes}", height
        tilt = tool_tilt_deg(quat)
        if tilt > lim.cone_deg + 1e-6:
            cone = lim.cone_deg
            return f"tool axis {tilt:.0f} deg from straight down, the cone allows {cone:g}", height
        if height < lim.table_clearance - BOX_TOLERANCE:
            return (
                f"tool within the table's clearance (its lowest point {height * 1e3:.1f} mm "
                f"above the table, the cell keeps {lim.table_clearance * 1e3:g} mm)"
            ), height
        return "", height

    def __call__(self, target: np.ndarray) -> Guarded:
        """The safe target nearest ``target`` for the next period."""
        if self._last is None or self._velocity is None:
            raise RobotError("the guard has no start pose: reset it before streaming targets")
        lim, dt, last, velocity = self.limits, self.period, self._last, self._velocity
        wanted = np.asarray(target, float)
        clipped: list[str] = []
        within = np.clip(wanted, lim.q_low, lim.q_high)
        if not np.allclose(within, wanted):
            clipped.append("joint limits")
        asked = (within - last) / dt
        slow = np.clip(asked, -lim.max_speed, lim.max_speed)
        step = lim.max_acceleration * dt
        chosen = velocity + np.clip(slow - velocity, -step, step)
        if not np.allclose(slow, asked):
            clipped.append("joint speed")
        elif not np.allclose(chosen, slow):
            clipped.append("acceleration")
        problem = self._unsafe(chosen)
        if problem:
            braking = self._braked(velocity)
            low, high = 0.0, 1.0
            for _ in range(BISECTIONS):
                middle = 0.5 * (low + high)
                if self._unsafe(braking + (chosen - braking) * middle):
                    high = middle
                else:
                    low = middle
            chosen = braking + (chosen - braking) * low
            clipped.append(problem.split(" (")[0])
        q = np.clip(last + chosen * dt, lim.q_low, lim.q_high)
        self._velocity = (q - last) / dt
        self._last = q
        self._height = self._inspect(q)[1]
        return Guarded(q=q, clipped=tuple(clipped))

    def _unsafe(self, velocity: np.ndarray) -> str:
        """What moving at ``velocity`` for one period, then braking, would break: every
        target of the braking, period by period as the guard would send them (a point
        between two of them, off their line in joint space, can leave the cone), and the
        tool's descent between them near the table."""
        assert self._last is not None
        lim = self.limits
        q, height = self._last + velocity * self.period, self._height
        while True:
            problem, lower = self._inspect(q)
            if problem:
                return problem
            descent = (height - lower) / self.period
            if (
                lower < lim.table_clearance + lim.approach_height
                and descent > lim.approach_speed + 1e-6
            ):
                return (
                    f"tool approaching the table too fast ({descent:.2f} m/s within "
                    f"{lim.approach_height * 1e3:g} mm of its clearance, the cell allows "
                    f"{lim.approach_speed:g} m/s)"
                )
            if not velocity.any():
                return ""
            velocity = self._braked(velocity)
            q, height = q + velocity * self.period, lower

    def _braked(self, velocity: np.ndarray) -> np.ndarray:
        """The joint velocity one period of full braking leaves: what the guard sends when
        it stops the arm, and so what :meth:`_unsafe` checks."""
        step = self.limits.max_acceleration * self.period
        return velocity - np.clip(velocity, -step, step)


def tool_tilt_deg(quat: np.ndarray) -> float:
    """Angle (deg) between the tool's z axis and straight down (-z of the base)."""
    x, y = np.asarray(quat, float)[1:3]
    tool_z_down = -(1.0 - 2.0 * (x * x + y * y))  # -(R[2, 2]): the tool z axis against -z
    return float(np.degrees(np.arccos(np.clip(tool_z_down, -1.0, 1.0))))
