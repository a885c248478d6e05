"""Acting one observation at a time from a policy that predicts action chunks.

With ``chunk > 1`` and ``temporal_ensemble`` set, a chunk is predicted at every step
and the executed action is the weighted average of every prediction made for this step
(temporal ensembling, as ACT does); without it each chunk is executed in turn before
looking again. With ``binary_gripper`` the gripper is commanded open or closed (at
:data:`~twinrl_sim.tasks.expert.GRIPPER_CLOSED`), with ``grasp_hold`` the arm holds
while it closes (:class:`~twinrl_robot.wrappers.HoldRule`), and with
``close_as_demonstrated`` a close waits until the tool is as low over the object as the
demonstrations close (:class:`~twinrl_learn.policy.close_height.CloseHeightRule`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from twinrl_learn.policy.close_height import CloseHeightRule
from twinrl_learn.policy.config import PolicyConfig
from twinrl_robot.wrappers import HoldRule
from twinrl_sim.tasks.expert import GRIPPER_CLOSED


class ChunkedActing:
    """The state of one episode's acting: the unexecuted rest of each chunk predicted
    so far, and the gripper's (see the module docstring). :meth:`reset` at each start."""

    def __init__(self, config: PolicyConfig) -> None:
        self.config = config
        self.reset()

    def reset(self) -> None:
        self._predictions: list[np.ndarray] = []
        self._hold = HoldRule()
        height = self.config.close_height
        self._close = None if height is None else CloseHeightRule(height)

    def act(
        self,
        observation: dict[str, Any],
        predict: Callable[[dict[str, Any]], np.ndarray],
        offsets: Callable[[dict[str, Any]], np.ndarray] | None = None,
    ) -> np.ndarray:
        """The action for ``observation``; ``predict`` maps a batch of one observation to
        its chunk (chunk, A) in physical units, ``offsets`` one observation to the
        objects' (objects, 3) positions relative to the TCP as the policy perceives them
        (needed for ``close_as_demonstrated``)."""
        action = self._next_action(observation, predict)
        if self.config.binary_gripper:
            action = np.array(action, copy=True)
            action[-1] = 1.0 if action[-1] >= GRIPPER_CLOSED else 0.0
        if self._close is not None and self.config.close_as_demonstrated and offsets:
            action = self._close(action, lambda: offsets(observation))
        if self.config.grasp_hold:
            action = self._hold(np.asarray(observation["observation.state"]), action)
        return action

    def _next_action(
        self, observation: dict[str, Any], predict: Callable[[dict[str, Any]], np.ndarray]
    ) -> np.ndarray:
        coefficient = self.config.temporal_ensemble
        # Each earlier prediction moves on by the step executed since.
        self._predictions = [rest[1:] for rest in self._predictions if len(rest) > 1]
        if coefficient is None and self._predictions:
            return self._predictions[0][0]
        chunk = predict({k: np.asarray(v)[None] for k, v in observation.items()})
        self._predictions.append(chunk)
        if coefficient is None:
            return chunk[0]
        for_now = np.stack([rest[0] for rest in self._predictions])  # oldest first
        weights = np.exp(-coefficient * np.arange(len(for_now)))
        return (weights @ for_now / weights.sum()).astype(np.float32)
