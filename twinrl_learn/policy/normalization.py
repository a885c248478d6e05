"""Normalisation with a dataset's statistics: states to zero mean and unit spread,
actions from their demonstrated range to the tanh's working range and back."""

from __future__ import annotations

import torch

from twinrl_learn.policy.config import ACTION_MARGIN


class Normalizer:
    """``stats`` maps ``state``, ``env`` and ``action`` to their ``mean``/``std`` (states)
    or ``min``/``max`` (actions); ``state_inputs`` picks the state entries the policy reads
    (empty: all)."""

    def __init__(self, stats: dict[str, dict[str, list[float]]], state_inputs: list[int]) -> None:
        self.stats = {k: {s: torch.tensor(v) for s, v in d.items()} for k, d in stats.items()}
        self.state_inputs = state_inputs

    def action_range(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Dataset min/max per action dimension; a constant dimension maps to itself."""
        low, high = self.stats["action"]["min"], self.stats["action"]["max"]
        constant = (high - low) < 1e-6
        return torch.where(constant, low - 1, low), torch.where(constant, high + 1, high)

    def normalize(self, key: str, values: torch.Tensor) -> torch.Tensor:
        """States to zero mean and unit std; actions from [min, max] to [-0.9, 0.9], so
        that demonstrated extremes stay where the tanh is not yet flat."""
        stats = self.stats[key]
        if key == "action":
            low, high = self.action_range()
            return ACTION_MARGIN * (2 * (values - low) / (high - low) - 1)
        normalized = (values - stats["mean"]) / stats["std"].clamp_min(1e-6)
        if key == "state" and self.state_inputs:
            normalized = normalized[..., self.state_inputs]
        return normalized

    def unnormalize_action(self, values: torch.Tensor) -> torch.Tensor:
        """Back to physical units, within the demonstrated range; a dimension that never
        varied in the data (e.g. tilting a top-down tool) keeps its constant value."""
        low, high = self.action_range()
        physical = (values / ACTION_MARGIN + 1) / 2 * (high - low) + low
        data_low, data_high = self.stats["action"]["min"], self.stats["action"]["max"]
        return torch.minimum(torch.maximum(physical, data_low), data_high)
