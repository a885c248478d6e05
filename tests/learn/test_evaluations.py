"""Real RL's evaluation points: each rate's interval, and whether a run kept its start."""

from __future__ import annotations

import pytest

from twinrl_learn.real_rl_progress import EvalPoint, kept_start


def _point(minutes: float, id_rate: float, count: int | None = 32) -> EvalPoint:
    counts = {} if count is None else {"ID": count, "OOD": count}
    return EvalPoint(round(600 * minutes), minutes, {"ID": id_rate, "OOD": 0.5}, 64, counts)


def test_an_evaluation_says_how_sure_its_rates_are() -> None:
    low, high = _point(0, 30 / 32).interval("ID")
    # Wilson's 95 % interval for 30 of 32: about 80-98 %.
    assert low == pytest.approx(0.7985, abs=1e-3) and high == pytest.approx(0.9827, abs=1e-3)
    wide = _point(0, 15 / 16, count=16).interval("ID")
    assert wide[0] < low and wide[1] > high  # fewer episodes, a wider interval
    assert _point(0, 30 / 32, count=None).interval("ID") is None  # an older run: no counts
    assert _point(0, 30 / 32).interval("nowhere") is None


def test_a_run_keeps_its_start_unless_it_ends_below_it_or_clearly_below_its_best() -> None:
    climbing = [_point(0, 28 / 32), _point(2, 30 / 32), _point(4, 29 / 32)]
    assert kept_start(climbing, "ID")  # 29 ends above 28; 30 is within 29's noise
    fell = [_point(0, 30 / 32), _point(2, 31 / 32), _point(4, 29 / 32)]
    assert not kept_start(fell, "ID")  # ended below where it started
    lost_best = [_point(0, 16 / 32), _point(2, 32 / 32), _point(4, 17 / 32)]
    assert not kept_start(lost_best, "ID")  # above its start, far below its best
    unknown = [_point(0, 0.5, None), _point(2, 0.75, None), _point(4, 0.75, None)]
    assert kept_start(unknown, "ID") and not kept_start([], "ID")
