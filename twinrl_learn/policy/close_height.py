"""Closing the gripper as low as the demonstrations close it.

A policy decides *when* to close from its inputs while the arm is still descending, and
a learnt decision is a few millimetres early: the image policy's failed grasps closed a
median 10 mm above the banana's centre, where the demonstrations close within 1 mm of
it, and the banana slipped out at the lift. What the demonstrations do is clear in their
data: at every close the tool stands a steady height above the object under it.

:func:`demonstrated_close_height` reads that height from the demonstrations (SFT stores
it as ``PolicyConfig.close_height``); :class:`CloseHeightRule` holds a close the policy
commands while the object it perceives under the tool is still more than
:data:`TOLERANCE` below that height, and descends onto it first (a few steps at most).
It reads only what the policy itself perceives: the pose estimator's estimates for an
image policy, the object poses for the privileged state policy.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from twinrl_sim.tasks.expert import GRIPPER_CLOSED

# An object counts as under the tool within this lateral distance (m) of the TCP.
LATERAL_REACH = 0.04
# How much higher (m) than the demonstrations' height a close may start.
TOLERANCE = 0.002
# The longest descent (m) of one held step, and how many steps one close may be held.
DESCENT_STEP = 0.01
MAX_HELD_STEPS = 4


def demonstrated_close_height(
    action: np.ndarray, episode_end: np.ndarray, offsets: np.ndarray
) -> float | None:
    """The median height (m) of the TCP above the centre of the object under it at the
    steps where the demonstrations' gripper command turns to close; None when no close
    has an object under the tool.

    ``action`` holds the frames' actions (the gripper last), ``episode_end`` each frame's
    episode end row (exclusive), ``offsets`` (N, objects, 3) each object's position minus
    the TCP's (m, base axes), as the policy perceives it; NaN rows are skipped."""
    closed = action[:, -1] >= GRIPPER_CLOSED
    starts = np.r_[True, episode_end[1:] != episode_end[:-1]]
    turns = np.flatnonzero(closed & (starts | ~np.r_[False, closed[:-1]]))
    heights = [h for row in turns if (h := height_under_tool(offsets[row])) is not None]
    return float(np.median(heights)) if heights else None


def height_under_tool(offsets: np.ndarray) -> float | None:
    """The TCP's height (m) above the centre of the object laterally nearest to it, from
    one frame's (objects, 3) offsets; None when none is within :data:`LATERAL_REACH`."""
    if not len(offsets) or np.isnan(offsets).any():
        return None
    lateral = np.linalg.norm(offsets[:, :2], axis=1)
    nearest = int(np.argmin(lateral))
    if lateral[nearest] > LATERAL_REACH:
        return None
    return float(-offsets[nearest, 2])


class CloseHeightRule:
    """Holds a commanded close until the tool is down at ``close_height`` above the
    object under it (see the module docstring). One per episode (:meth:`reset` at its
    start); call it with each action about to be executed and a function that returns the
    current (objects, 3) offsets, which it calls only while a close is pending."""

    def __init__(self, close_height: float) -> None:
        self.close_height = close_height
        self.reset()

    def reset(self) -> None:
        self._held = 0
        self._closing = False

    def __call__(self, action: np.ndarray, offsets: Callable[[], np.ndarray]) -> np.ndarray:
        if action[-1] < GRIPPER_CLOSED:
            self._held, self._closing = 0, False
            return action
        if self._closing or self._held >= MAX_HELD_STEPS:
            self._closing = True
            return action
        height = height_under_tool(offsets())
        excess = None if height is None else height - self.close_height
        if excess is None or excess <= TOLERANCE:
            self._closing = True
            return action
        self._held += 1
        descend = np.zeros_like(action)
        descend[2] = -min(excess, DESCENT_STEP)
        return descend  # the gripper stays open (0) while the arm goes down
