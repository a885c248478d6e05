"""Which camera frame each control step of a live episode saw (see
:mod:`twinrl_data.streams`)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def frames_of_steps(
    frames: Mapping[int, tuple[int, bytes]], step_times: list[int]
) -> dict[int, tuple[int, bytes]]:
    """A live episode's camera, every frame at its own rate, as one frame per step: the
    newest frame captured by the step's time (what the step's observation saw), or the
    first frame for steps before it."""
    if not frames:
        return {}
    ordered = sorted(frames.values())
    times = np.array([t for t, _ in ordered])
    chosen = np.clip(np.searchsorted(times, step_times, side="right") - 1, 0, len(ordered) - 1)
    return {step: ordered[index] for step, index in enumerate(chosen)}
