"""The two timelines a twinrl Rerun recording of an episode is on: ``step`` (the
control step) and ``time`` (seconds since the episode began, at its logged rate)."""

from __future__ import annotations

import numpy as np
import rerun as rr


def step_times(count: int, fps: float) -> list[rr.TimeColumn]:
    """Both timelines for ``count`` steps at ``fps``, as columns for ``rr.send_columns``."""
    steps = np.arange(count)
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("time", duration=steps / fps)]


def set_step(recording: rr.RecordingStream, step: int, fps: float) -> None:
    """Put ``recording``'s clock at ``step`` on both timelines."""
    recording.set_time("step", sequence=int(step))
    recording.set_time("time", duration=step / fps)
