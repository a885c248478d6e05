"""Evaluation by region: roll a policy out over a grid of configurations, in the twin or
the plant, log every rollout, and map success over the table.

The grid covers the bounding box of the task's ID and OOD regions; each cell whose
centre lies in a region is evaluated with the target (where the object's centre ends
up) at the cell centre, the object placed in the same region. Outputs in ``out``::

    out/session/        every rollout as an episode (source ``eval``)
    out/eval.json       {"success_rate": {"ID": x, "OOD": y}, "episodes": n, "cells": [...]}
    out/heatmap.png     success over the table, regions outlined (like TwinRL's Fig. 2b)
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_data.executor import cluster_address, make_executor
from twinrl_data.recorder import EpisodeFolder, Recorder
from twinrl_data.schema import EpisodeMeta
from twinrl_data.session import EPISODES, Session
from twinrl_learn.errors import LearnError
from twinrl_learn.runners import Runner, RunnerSource
from twinrl_robot.backends import open_robot
from twinrl_robot.cell_file import load_cell
from twinrl_robot.loop import privileged_success, run_episode
from twinrl_sim.tasks import REGION_NAMES, TaskConfig, make_task, task_on_twin


@dataclass
class Cell:
    x: float
    y: float
    region: str
    episodes: int = 0
    successes: int = 0

    @property
    def rate(self) -> float:
        return self.successes / max(self.episodes, 1)


@dataclass
class EvalReport:
    task: str
    world: str
    policy: str
    cells: list[Cell]

    def success_rate(self) -> dict[str, float]:
        rates = {}
        for region in REGION_NAMES:
            inside = [c for c in self.cells if c.region == region]
            if inside:
                rates[region] = sum(c.successes for c in inside) / max(
                    sum(c.episodes for c in inside), 1
                )
        return rates

    @property
    def episodes(self) -> int:
        return sum(c.episodes for c in self.cells)

    def region_episodes(self) -> dict[str, int]:
        """Episodes per region (what each success rate is over)."""
        counts = {r: sum(c.episodes for c in self.cells if c.region == r) for r in REGION_NAMES}
        return {r: n for r, n in counts.items() if n}

    def to_json(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "world": self.world,
            "policy": self.policy,
            "success_rate": self.success_rate(),
            "episodes": self.episodes,
            "cells": [asdict(c) | {"success_rate": c.rate} for c in self.cells],
        }


def grid_cells(task_name: str, grid: tuple[int, int]) -> list[Cell]:
    """Cell centres over the regions' bounding box that fall inside a region."""
    task = make_task(task_name)
    areas = list(task.regions.values())
    x_low, x_high = min(a.x[0] for a in areas), max(a.x[1] for a in areas)
    y_low, y_high = min(a.y[0] for a in areas), max(a.y[1] for a in areas)
    cells = []
    for i in range(grid[0]):
        for j in range(grid[1]):
            x = x_low + (i + 0.5) * (x_high - x_low) / grid[0]
            y = y_low + (j + 0.5) * (y_high - y_low) / grid[1]
            region = next((name for name, a in task.regions.items() if a.contains(x, y)), None)
            if region is not None:
                cells.append(Cell(x=x, y=y, region=region))
    return cells


def _cell_config(task, cell: Cell, rng: np.random.Generator) -> TaskConfig:
    area = task.region(cell.region)
    for _ in range(1000):
        obj = area.sample(rng)
        if np.hypot(obj[0] - cell.x, obj[1] - cell.y) >= task.min_separation:
            return TaskConfig(
                object=(*obj, rng.uniform(*task.object_yaw)),
                target=(cell.x, cell.y, rng.uniform(*task.target_yaw)),
            )
    raise RuntimeError(
        f"no object position fits region {cell.region} with the target at ({cell.x}, {cell.y})"
    )


def evaluate(
    runner: Runner,
    task_name: str,
    *,
    world: str = "twin",
    effects: str | Path | dict | None = None,
    grid: tuple[int, int] = (8, 8),
    episodes: int = 1,
    seed: int = 0,
    out: str | Path,
    on_episode: Callable[[Cell, bool], None] | None = None,
    cell_file: str | Path | None = None,
    emulated: bool = False,
    twin: str | None = None,
    workers: int | None = 1,
    cluster: str = "",
) -> EvalReport:
    """Roll ``runner`` out ``episodes`` times per grid cell; write the outputs to ``out``.

    ``world`` ``real`` is the arm of ``cell_file``; success is judged from the task's
    ground truth, which only an ``emulated`` cell lends (a real cell refuses it). The task
    runs on ``twin`` (a built-in cell or a scene spec file; default: the cell file's twin,
    else the task's own scene), whose kinematics and limits a cell's arm runs with.
    In the twin, ``workers`` worker processes (or Ray tasks where ``cluster`` says:
    :func:`twinrl_data.executor.cluster_address`) share the episodes, with the same
    results as one: every episode's configuration and seed are drawn before any runs."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise LearnError(f"{out} exists and is not empty; choose another output folder")
    spread = cluster_address(cluster) is not None or workers != 1
    if spread and world != "twin":
        raise SettingError(
            "workers",
            "shares the episodes in the twin only (the plant's sensor noise runs on from "
            "one episode to the next); evaluate the plant with one worker",
        )
    if twin is None and cell_file is not None:
        twin = load_cell(cell_file).twin
    task = make_task(task_name, task_on_twin(task_name, twin) if twin is not None else None)
    cells = grid_cells(task_name, grid)
    rng = np.random.default_rng(seed)
    # Every episode's configuration and seed, drawn in grid order before any runs.
    draws = []
    for i, cell in enumerate(cells):
        for _ in range(episodes):
            config = _cell_config(task, cell, rng)
            seed_n = int(rng.integers(2**31))
            draws.append(_Episode(len(draws), i, cell.region, config, seed_n))

    def count(draw: _Episode, success: bool) -> None:
        cells[draw.cell].episodes += 1
        cells[draw.cell].successes += success
        if on_episode is not None:
            on_episode(cells[draw.cell], success)

    if spread:
        _evaluate_spread(runner, task_name, twin, draws, out / "session", workers, cluster, count)
    else:
        robot = open_robot(
            world,
            task,
            effects=effects,
            seed=seed,
            cameras=runner.cameras,
            cell=cell_file,
            emulated=emulated,
        )
        recorder = Recorder(Session.create(out / "session"))
        # Runners re-seed torch for every episode; a caller that is training (real RL,
        # mining between its episodes) gets its random stream back as it was.
        torch_state = torch.get_rng_state()
        try:
            for draw in draws:
                count(draw, _run(robot, runner, task, world, draw, recorder).success)
        finally:
            robot.close()
            torch.set_rng_state(torch_state)
    report = EvalReport(task=task_name, world=world, policy=runner.name, cells=cells)
    write_text_atomic(out / "eval.json", json.dumps(report.to_json(), indent=1))
    plot_heatmap(report, grid, out / "heatmap.png")
    return report


@dataclass(frozen=True)
class _Episode:
    index: int  # in the evaluation's order
    cell: int  # index of its grid cell
    region: str
    config: TaskConfig
    seed: int  # the runner's


def _run(robot, runner: Runner, task, world: str, draw: _Episode, recorder: Recorder):
    meta = task.episode_meta(
        source="eval",
        world=world,
        names=robot.names,
        config=draw.config,
        region=draw.region,
        policy=runner.name,
    )
    source = RunnerSource(runner, seed=draw.seed)
    judge = privileged_success(robot)
    return run_episode(robot, source, task, draw.config, judge=judge, recorder=recorder, meta=meta)


@dataclass(frozen=True)
class _Chunk:
    """Consecutive episodes of a twin evaluation: what a worker needs to run them."""

    runner: Runner
    task: str
    twin: str | None
    episodes: list[_Episode]
    folder: str  # the session's episodes folder


def _evaluate_spread(
    runner: Runner,
    task_name: str,
    twin: str | None,
    draws: list[_Episode],
    folder: Path,
    workers: int | None,
    cluster: str,
    count: Callable[[_Episode, bool], None],
) -> None:
    """The episodes in chunks on an executor, added to the session ``folder`` in order."""
    with make_executor(workers, initializer=single_threaded, cluster=cluster) as executor:
        session = Session.create(folder)
        size = max(1, -(-len(draws) // (4 * executor.workers)))  # a few chunks per worker
        episodes = str(session.path / EPISODES)
        jobs = [
            _Chunk(runner, task_name, twin, draws[i : i + size], episodes)
            for i in range(0, len(draws), size)
        ]
        for results in executor.map(_run_chunk, jobs):
            for draw, (path, meta, length, success) in results:
                session.register(Path(path), EpisodeMeta.from_dict(meta), length)
                count(draw, success)


def single_threaded() -> None:
    """A worker's torch on one thread: the workers share the cores."""
    torch.set_num_threads(1)


def _run_chunk(chunk: _Chunk) -> list[tuple[_Episode, tuple[str, dict, int, bool]]]:
    task = make_task(chunk.task, task_on_twin(chunk.task, chunk.twin) if chunk.twin else None)
    robot = open_robot("twin", task, cameras=chunk.runner.cameras)
    results = []
    try:
        for draw in chunk.episodes:
            recorder = Recorder(EpisodeFolder(chunk.folder, prefix=f"{draw.index:05d}_"))
            outcome = _run(robot, chunk.runner, task, "twin", draw, recorder)
            assert recorder.saved is not None
            saved = (str(outcome.path), recorder.saved.to_dict(), outcome.steps, outcome.success)
            results.append((draw, saved))
    finally:
        robot.close()
    return results


def plot_heatmap(report: EvalReport, grid: tuple[int, int], path: Path) -> None:
    """Success rate per cell over the table (robot at the bottom), regions outlined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    task = make_task(report.task)
    areas = list(task.regions.values())
    x_low, x_high = min(a.x[0] for a in areas), max(a.x[1] for a in areas)
    y_low, y_high = min(a.y[0] for a in areas), max(a.y[1] for a in areas)
    values = np.full((grid[0], grid[1]), np.nan)
    for cell in report.cells:
        i = min(grid[0] - 1, int((cell.x - x_low) / (x_high - x_low) * grid[0]))
        j = min(grid[1] - 1, int((cell.y - y_low) / (y_high - y_low) * grid[1]))
        values[i, j] = cell.rate
    fig, ax = plt.subplots(figsize=(6, 4.2), dpi=120)
    image = ax.imshow(
        values,
        origin="lower",
        extent=(y_low, y_high, x_low, x_high),
        vmin=0,
        vmax=1,
        cmap="RdYlGn",
        aspect="equal",
    )
    for name, area in task.regions.items():
        ax.add_patch(
            Rectangle(
                (area.y[0], area.x[0]),
                area.y[1] - area.y[0],
                area.x[1] - area.x[0],
                fill=False,
                lw=2,
                ec="black",
            )
        )
        rate = report.success_rate().get(name)
        label = f"{name}: {100 * rate:.0f} %" if rate is not None else name
        ax.text(
            (area.y[0] + area.y[1]) / 2,
            area.x[0] + 0.01,
            label,
            ha="center",
            va="bottom",
            fontsize=9,
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
    ax.set_xlabel("y (m, base frame)")
    ax.set_ylabel("x (m)")
    ax.set_title(f"{report.task} in the {report.world}\n{report.policy}", fontsize=9, pad=8)
    fig.colorbar(image, ax=ax, label="success rate")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
