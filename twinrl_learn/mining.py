"""Stage III support: find the configurations where the current policy fails in the twin.

The policy is evaluated in the twin over a grid of configurations (or logged twin
evaluations are reused from the catalog); each grid cell's success rate gets a Beta
posterior (uniform prior) from its successes and failures. The target set is
``S_target = {cells whose posterior mean success < tau}``, ranked so that
*failure-prone yet informative* cells come first: the score is the probability that
the cell is below ``tau`` times the outcome variance ``p (1 - p)`` of its posterior
mean (zero for cells that are solved or hopeless), with a small floor so hopeless
cells still follow. Each selected cell yields one reset target: the configuration of
a failed episode in it (the exact initial state the policy got wrong).

``targets.json``::

    {"task": ..., "policy": ..., "tau": ..., "episodes": n,
     "cells": [{"x", "y", "region", "successes", "episodes", "success_mean",
                "success_low", "success_high", "p_below_tau", "score"}, ...],
     "targets": [{"config": {...}, "region", "x", "y", "estimated_success", "score"}, ...]}
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import beta as beta_dist

from twinrl_data.atomic import write_text_atomic
from twinrl_data.catalog import query
from twinrl_data.errors import SettingError
from twinrl_data.mcap_log import read_meta
from twinrl_data.session import Session
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate, grid_cells
from twinrl_learn.runners import Runner
from twinrl_sim.tasks import make_task

HOPELESS_FLOOR = 0.05  # share of the score kept by cells whose success is near zero


@dataclass
class CellEstimate:
    x: float
    y: float
    region: str
    successes: int
    episodes: int
    success_mean: float
    success_low: float  # 5 % posterior quantile
    success_high: float  # 95 % posterior quantile
    p_below_tau: float
    score: float


@dataclass
class Target:
    config: dict[str, Any]
    region: str
    x: float
    y: float
    estimated_success: float
    score: float


def estimate_cell(
    x: float, y: float, region: str, successes: int, episodes: int, tau: float
) -> CellEstimate:
    """Beta(1 + s, 1 + f) posterior of one cell's success rate and its mining score."""
    a, b = 1 + successes, 1 + episodes - successes
    mean = a / (a + b)
    below = float(beta_dist.cdf(tau, a, b))
    informative = mean * (1 - mean) * 4  # 1 at p = 0.5, 0 at p = 0 or 1
    score = below * (HOPELESS_FLOOR + (1 - HOPELESS_FLOOR) * informative)
    return CellEstimate(
        x=x,
        y=y,
        region=region,
        successes=successes,
        episodes=episodes,
        success_mean=mean,
        success_low=float(beta_dist.ppf(0.05, a, b)),
        success_high=float(beta_dist.ppf(0.95, a, b)),
        p_below_tau=below,
        score=score,
    )


def select_targets(
    outcomes: list[tuple[dict[str, Any], str, bool]],
    task_name: str,
    grid: tuple[int, int],
    *,
    tau: float = 0.8,
    k: int = 20,
) -> tuple[list[CellEstimate], list[Target]]:
    """Cells and ranked targets from ``(config, region, success)`` outcomes; each
    outcome falls into the grid cell nearest its target position."""
    if not 0 < tau <= 1:
        raise SettingError("tau", f"must be in (0, 1], got {tau}")
    if k < 1:
        raise SettingError("k", f"must be at least 1, got {k}")
    cells = grid_cells(task_name, grid)
    if not cells:
        raise LearnError(f"the {grid[0]}x{grid[1]} grid has no cell inside a region")
    centres = np.array([[c.x, c.y] for c in cells])
    members: list[list[tuple[dict[str, Any], bool]]] = [[] for _ in cells]
    for config, _, success in outcomes:
        target = np.asarray(config["target"][:2], float)
        members[int(np.argmin(np.linalg.norm(centres - target, axis=1)))].append((config, success))
    estimates, targets = [], []
    for cell, runs in zip(cells, members, strict=True):
        wins = sum(s for _, s in runs)
        estimate = estimate_cell(cell.x, cell.y, cell.region, wins, len(runs), tau)
        estimates.append(estimate)
        failed = [c for c, s in runs if not s]
        if failed and estimate.success_mean < tau:
            targets.append(
                Target(
                    config=failed[0],
                    region=cell.region,
                    x=cell.x,
                    y=cell.y,
                    estimated_success=estimate.success_mean,
                    score=estimate.score,
                )
            )
    targets.sort(key=lambda t: -t.score)
    return estimates, targets[:k]


def logged_outcomes(
    catalog: str | Path, task: str, policy: str
) -> list[tuple[dict[str, Any], str, bool]]:
    """Twin evaluations of ``policy`` on ``task`` already in the catalog."""
    quoted = policy.replace("'", "''")
    rows = query(catalog, task=task, source="eval", world="twin", where=f"policy = '{quoted}'")
    outcomes = [
        (json.loads(config), region, bool(success))
        for config, region, success in zip(
            rows.column("config").to_pylist(),
            rows.column("region").to_pylist(),
            rows.column("success").to_pylist(),
            strict=True,
        )
    ]
    if not outcomes:
        raise LearnError(
            f"the catalog {catalog} has no twin evaluations of '{policy}' on {task}; "
            "evaluate it in the twin and index those episodes first, or mine without "
            "`episodes_from`"
        )
    return outcomes


def session_outcomes(session: Session) -> list[tuple[dict[str, Any], str, bool]]:
    """Outcomes of the episodes of an evaluation session."""
    metas = [read_meta(p) for p in session.episode_paths()]
    return [(m.config, m.region or "", bool(m.success)) for m in metas]


def mine(
    runner: Runner,
    task: str,
    *,
    out: str | Path,
    grid: tuple[int, int] = (8, 8),
    episodes: int = 2,
    tau: float = 0.8,
    k: int = 20,
    seed: int = 0,
    catalog: str | Path | None = None,
    twin: str | None = None,
    workers: int | None = 1,
    cluster: str = "",
) -> dict[str, Any]:
    """Evaluate (or look up) ``runner`` in the twin and write the target list to ``out``
    (a ``.json`` file; the evaluation, when run, goes beside it). ``twin``: the cell's
    twin to mine in (a built-in cell or a scene spec file; default: the task's scene).
    ``workers`` and ``cluster`` spread the grid's episodes (:func:`evaluate`); the
    targets are the same whatever they are."""
    out = Path(out)
    if out.suffix != ".json":
        raise SettingError("out", f"must be a .json file, got {out}")
    if out.exists():
        raise LearnError(f"{out} exists; choose another file (targets are never overwritten)")
    make_task(task)
    if catalog is not None:
        outcomes = logged_outcomes(catalog, task, runner.name)
    else:
        evaluation = out.with_suffix("")
        evaluate(
            runner,
            task,
            world="twin",
            grid=grid,
            episodes=episodes,
            seed=seed,
            out=evaluation,
            twin=twin,
            workers=workers,
            cluster=cluster,
        )
        outcomes = session_outcomes(Session(evaluation / "session"))
    cells, targets = select_targets(outcomes, task, grid, tau=tau, k=k)
    result = {
        "task": task,
        "policy": runner.name,
        "tau": tau,
        "episodes": len(outcomes),
        "cells": [asdict(c) for c in cells],
        "targets": [asdict(t) for t in targets],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, json.dumps(result, indent=1))
    return result


def load_targets(path: str | Path) -> list[Target]:
    """The ordered reset targets of a ``targets.json``."""
    path = Path(path)
    if not path.is_file():
        raise LearnError(f"targets file {path} does not exist; create it with `twinrl mine`")
    try:
        data = json.loads(path.read_text())
        return [Target(**t) for t in data["targets"]]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise LearnError(f"{path} is not a targets file written by `twinrl mine` ({err})") from None
