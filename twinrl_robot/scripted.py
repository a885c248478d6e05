"""Run a task's scripted expert in the twin or in the plant and tally success by region."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from twinrl_robot.plant import Plant
from twinrl_sim.env import TwinEnv
from twinrl_sim.tasks import REGION_NAMES, TaskConfig, make_task

World = Literal["twin", "plant"]
WORLDS: tuple[str, ...] = ("twin", "plant")


@dataclass(frozen=True)
class ExpertEpisode:
    region: str
    config: dict[str, list[float]]
    success: bool
    steps: int


@dataclass(frozen=True)
class ExpertReport:
    """Outcome of a scripted-expert run."""

    task: str
    world: str
    episodes: tuple[ExpertEpisode, ...]

    def success_rate(self) -> dict[str, float]:
        """Success rate per region that was run (regions not run are omitted)."""
        rates = {}
        for region in REGION_NAMES:
            outcomes = [e.success for e in self.episodes if e.region == region]
            if outcomes:
                rates[region] = float(np.mean(outcomes))
        return rates

    def counts(self) -> dict[str, int]:
        return {r: sum(e.region == r for e in self.episodes) for r in self.success_rate()}

    def to_json(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "world": self.world,
            "episodes": len(self.episodes),
            "success_rate": self.success_rate(),
        }

    def save(self, path: str | Path) -> None:
        Path(path).write_text(
            json.dumps({**self.to_json(), "runs": [asdict(e) for e in self.episodes]}, indent=1)
        )


class _TwinWorld:
    def __init__(self, task: str) -> None:
        self.env = TwinEnv(task)
        self.task = self.env.task
        self._success = False

    def reset(self, config: TaskConfig) -> dict[str, np.ndarray]:
        obs, info = self.env.reset(options={"config": config})
        self._success = info["success"]
        return obs

    def step(self, action: np.ndarray) -> dict[str, np.ndarray]:
        obs, _, _, _, info = self.env.step(action)
        self._success = info["success"]
        return obs

    @property
    def success(self) -> bool:
        return self._success

    def close(self) -> None:
        self.env.close()


class _PlantWorld:
    def __init__(self, task: str, effects: dict | str | Path | None, seed: int) -> None:
        self.plant = Plant(task, effects=effects, seed=seed)
        self.task = self.plant.task

    def reset(self, config: TaskConfig) -> dict[str, np.ndarray]:
        return self.plant.reset(config)

    def step(self, action: np.ndarray) -> dict[str, np.ndarray]:
        self.plant.act(action)
        return self.plant.observe()

    @property
    def success(self) -> bool:
        return self.plant.success

    def close(self) -> None:
        self.plant.close()


def run_scripted_expert(
    task: str,
    *,
    world: World = "twin",
    episodes: int = 20,
    regions: tuple[str, ...] = REGION_NAMES,
    effects: dict | str | Path | None = None,
    seed: int = 0,
    on_episode: Callable[[ExpertEpisode], None] | None = None,
) -> ExpertReport:
    """Run ``episodes`` expert episodes per region in ``world`` (deterministic per seed).

    ``effects`` only applies to the plant (``None``: the built-in plant's hidden effects).
    """
    if world not in WORLDS:
        raise ValueError(f"world must be one of {', '.join(WORLDS)}, got '{world}'")
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    if world == "twin" and effects is not None:
        raise ValueError("effects apply to the plant only; the twin runs its own scene spec")
    spec_task = make_task(task)
    for region in regions:
        spec_task.region(region)
    sim = _TwinWorld(task) if world == "twin" else _PlantWorld(task, effects, seed)
    rng = np.random.default_rng(seed)
    results = []
    try:
        for r, region in enumerate(regions):
            for i in range(episodes):
                config = sim.task.sample_config(rng, region)
                expert = sim.task.expert(config, np.random.default_rng([seed, r, i]))
                obs = sim.reset(config)
                steps = 0
                while steps < sim.task.max_steps and not sim.success:
                    obs = sim.step(expert.act(obs))
                    steps += 1
                episode = ExpertEpisode(region, config.to_dict(), sim.success, steps)
                results.append(episode)
                if on_episode is not None:
                    on_episode(episode)
    finally:
        sim.close()
    return ExpertReport(task=task, world=world, episodes=tuple(results))
