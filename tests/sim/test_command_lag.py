"""The command link's lag, measured from the targets a controller echoes: recovered from
segments as a driver streams them, with the jitter and quantisation of a real log; from
the controller's every package, a host's late starts are seen too."""

from __future__ import annotations

import numpy as np
import pytest

from twinrl_data.schema import (
    ACTION,
    CONTROLLER_TARGET,
    CONTROLLER_TIME,
    JOINT_TARGET,
    STATE,
    Episode,
    EpisodeMeta,
    Samples,
)
from twinrl_sim.gap.command_lag import CONTROLLER_STREAM, command_lag

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


def _live_episode(rng: np.random.Generator, lag: float, late: float, steps: int = 60) -> Episode:
    """A live episode as a UR cell logs it: steps measured at jittered controller times,
    and the controller's every package (500 Hz, written with six decimals). The host
    starts each segment ``late`` and runs it faster to end on time; the link adds
    ``lag`` to everything."""
    moves = rng.normal(0.0, 0.02, (steps, 6)) * (rng.random((steps, 1)) > 0.2)
    sent = np.cumsum(moves, axis=0) + rng.uniform(-1, 1, 6)
    clock = np.arange(0.0, steps / FPS + 0.05, 0.002)
    # Each step is measured from a package: its time is one of the packages' times.
    jittered = np.arange(steps) / FPS + np.abs(rng.normal(0.0, 0.003, steps))
    rows = clock[np.searchsorted(clock, jittered)]

    def target(t: np.ndarray) -> np.ndarray:
        """Segment k runs from sent[k - 1] to sent[k], from row k's time plus ``late``
        to row k + 1's (row 0 holds where the arm was reset)."""
        k = np.clip(np.searchsorted(rows, t, side="right") - 1, 0, steps - 2)
        start = rows[k] + late
        fraction = np.clip((t - start) / (rows[k + 1] - start), 0.0, 1.0)[:, None]
        before = sent[np.maximum(k - 1, 0)]
        return np.round(before + (sent[k] - before) * fraction, 6)

    packages = target(clock - lag)
    data = {
        STATE: np.zeros((steps, 20), np.float32),
        ACTION: np.zeros((steps, 7), np.float32),
        JOINT_TARGET: sent.astype(np.float32),
        CONTROLLER_TIME: rows[:, None].astype(np.float32),
        CONTROLLER_TARGET: target(rows - lag).astype(np.float32),
    }
    names = [f"target_q.{j}" for j in range(6)]
    stream = Samples(names, clock, packages.astype(np.float32), clock + 1234.5)
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=FPS)
    return Episode(meta, data, samples={CONTROLLER_STREAM: stream})


@pytest.mark.parametrize("lag", [0.0, 0.004])
def test_with_the_controllers_packages_a_hosts_late_starts_are_measured(lag: float) -> None:
    # A segment started 20 ms late and run faster to end on time trails the line by
    # 10 ms on average: the packages show it, the segments' ends do not.
    rng = np.random.default_rng(3)
    late = [_live_episode(rng, lag, 0.02) for _ in range(3)]
    assert command_lag(late) == pytest.approx(lag + 0.01, abs=5e-4)
    ends_only = [Episode(e.meta, e.data) for e in late]
    assert command_lag(ends_only) < lag + 0.002  # the link's lag alone, sped up
    on_time = [_live_episode(rng, lag, 0.0) for _ in range(3)]
    assert command_lag(on_time) == pytest.approx(lag, abs=5e-4)
