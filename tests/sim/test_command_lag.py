"""The command link's lag, measured from the targets a controller echoes: recovered from
segments as a driver streams them, with the jitter and quantisation of a real log."""

from __future__ import annotations

import numpy as np
import pytest

from twinrl_data.schema import (
    ACTION,
    CONTROLLER_TARGET,
    JOINT_TARGET,
    STATE,
    Episode,
    EpisodeMeta,
)
from twinrl_sim.gap.command_lag import command_lag

FPS = 10.0


def _episode(rng: np.random.Generator, lag: float | None, steps: int = 60) -> Episode:
    """Joint targets on a random walk (some steps standing still), and, when ``lag`` is
    given, what a controller echoes when each step is measured: the point of the segment
    ``lag`` (jittered by a few ms, as a host's timing is) before its end."""
    moves = rng.normal(0.0, 0.02, (steps, 6)) * (rng.random((steps, 1)) > 0.2)
    sent = np.cumsum(moves, axis=0) + rng.uniform(-1, 1, 6)
    data = {
        STATE: np.zeros((steps, 20), np.float32),
        ACTION: np.zeros((steps, 7), np.float32),
        JOINT_TARGET: sent.astype(np.float32),
    }
    if lag is not None:
        echoed = sent.copy()  # row 0: the arm at rest where it was reset
        for row in range(1, steps):
            previous = sent[row - 2] if row >= 2 else sent[0]
            late = np.clip(lag + rng.normal(0.0, 0.002), 0.0, None) * FPS
            echoed[row] = sent[row - 1] - late * (sent[row - 1] - previous)
        echoed += rng.normal(0.0, 1e-5, echoed.shape)  # the encoders' last digits
        data[CONTROLLER_TARGET] = echoed.astype(np.float32)
    return Episode(EpisodeMeta(task="pick_place", source="teleop", world="real", fps=FPS), data)


@pytest.mark.parametrize("lag", [0.0, 0.003, 0.012])
def test_the_lag_is_recovered_from_echoed_targets(lag: float) -> None:
    rng = np.random.default_rng(7)
    episodes = [_episode(rng, lag) for _ in range(3)]
    assert command_lag(episodes) == pytest.approx(lag, abs=5e-4)


def test_a_log_without_echoed_targets_has_no_lag() -> None:
    rng = np.random.default_rng(1)
    assert command_lag([_episode(rng, None), _episode(rng, None)]) is None


def test_an_arm_that_stood_still_has_no_lag_to_measure() -> None:
    rng = np.random.default_rng(2)
    episode = _episode(rng, 0.005)
    episode.data[JOINT_TARGET][:] = episode.data[JOINT_TARGET][0]
    episode.data[CONTROLLER_TARGET][:] = episode.data[JOINT_TARGET][0]
    assert command_lag([episode]) is None
