"""A real-RL run's progress: its evaluation points, the curve of success against plant
minutes, and the control loop's timing."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinrl_learn.errors import LearnError
from twinrl_sim.tasks import REGION_NAMES

EVALUATIONS_FILE = "evaluations.json"


CONFIDENCE = 0.95  # of the intervals around an evaluation's success rates


@dataclass
class EvalPoint:
    """One evaluation of the policy during real RL."""

    plant_steps: int
    plant_minutes: float
    success_rate: dict[str, float]
    episodes: int  # evaluation episodes run (0 on a UR cell: its own episodes score it)
    region_episodes: dict[str, int] = field(default_factory=dict)  # each rate's; {}: older

    def interval(self, region: str) -> tuple[float, float] | None:
        """The 95 % Wilson interval of ``region``'s success rate over its episodes (None
        where they were not counted)."""
        count = self.region_episodes.get(region, 0)
        if not count or region not in self.success_rate:
            return None
        from scipy.stats import binomtest

        wins = round(self.success_rate[region] * count)
        ci = binomtest(wins, count).proportion_ci(CONFIDENCE, method="wilson")
        return float(ci.low), float(ci.high)


def kept_start(evaluations: list[EvalPoint], region: str) -> bool:
    """Whether a run ended at least where it started in ``region`` and its last
    evaluation is within noise of its best (the best rate inside the last's 95 %
    interval; without counts, equal to it)."""
    rates = [e.success_rate.get(region, 0.0) for e in evaluations]
    if not rates:
        return False
    interval = evaluations[-1].interval(region)
    high = interval[1] if interval is not None else rates[-1]
    return rates[-1] >= rates[0] and max(rates) <= high + 1e-9


def loop_timing(periods: list[float]) -> dict[str, float | int]:
    """The control loop's period (s) over ``periods``: median, 99th percentile, worst."""
    if not periods:
        return {"steps": 0}
    values = np.asarray(periods)
    return {
        "steps": len(values),
        "p50_s": float(np.percentile(values, 50)),
        "p99_s": float(np.percentile(values, 99)),
        "max_s": float(values.max()),
    }


def minutes_to(evaluations: list[EvalPoint], region: str, level: float = 0.95) -> float | None:
    """Plant minutes at the first evaluation with ``region`` success >= ``level``."""
    for point in evaluations:
        if point.success_rate.get(region, 0.0) >= level:
            return point.plant_minutes
    return None


def load_evaluations(folder: str | Path) -> list[EvalPoint]:
    path = Path(folder) / EVALUATIONS_FILE
    if not path.is_file():
        raise LearnError(f"{folder} holds no {EVALUATIONS_FILE}; it is not a real-RL run")
    return [EvalPoint(**p) for p in json.loads(path.read_text())]


def plot_evaluations(evaluations: list[EvalPoint], path: Path, *, title: str = "") -> None:
    """Evaluation success per region against plant minutes, shaded over each
    evaluation's 95 % interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    for region in REGION_NAMES:
        points = [p for p in evaluations if region in p.success_rate]
        xs = [p.plant_minutes for p in points]
        (line,) = ax.plot(
            xs, [p.success_rate[region] for p in points], marker="o", ms=3, lw=1.6, label=region
        )
        intervals = [p.interval(region) for p in points]
        if points and all(i is not None for i in intervals):
            low, high = zip(*intervals, strict=True)  # type: ignore[misc]
            ax.fill_between(xs, low, high, color=line.get_color(), alpha=0.15, lw=0)
    ax.axhline(0.95, color="grey", lw=0.8, ls="--")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("plant minutes (10 Hz robot steps)")
    ax.set_ylabel("evaluation success")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
