"""Run a task's scripted expert in the twin or in the plant and tally success by region."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from twinrl_data.schema import EFFORT, EpisodeMeta, step_record
from twinrl_data.session import Session
from twinrl_robot.plant import Plant
from twinrl_sim.env import TwinEnv
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import REGION_NAMES, Progress, TaskConfig, make_task

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
    source, world = "twin_demo", "twin"

    def __init__(self, task: str, images: bool, scene: SceneSpec | None) -> None:
        self.env = TwinEnv(task, scene=scene, images=images)
        self.task = self.env.task
        self.names = self.env.cell.contract_names()
        self._success = False

    def reset(self, config: TaskConfig) -> dict[str, np.ndarray]:
        obs, info = self.env.reset(options={"config": config})
        self._success = info["success"]
        return obs

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
        obs, _, _, _, info = self.env.step(action)
        self._success = info["success"]
        return obs, info["command.joint_target"]

    @property
    def success(self) -> bool:
        return self._success

    def close(self) -> None:
        self.env.close()


class _PlantWorld:
    # The scripted expert stands in for a human teleoperating the (stand-in) real cell,
    # whose controller reports joint torques as a UR's does (the gap workflow uses them).
    source, world = "teleop", "plant"

    def __init__(
        self,
        task: str,
        effects: dict | str | Path | None,
        seed: int,
        images: bool,
        scene: SceneSpec | None,
    ) -> None:
        self.plant = Plant(
            make_task(task, scene),
            effects=effects,
            seed=seed,
            images=("front", "wrist") if images else (),
        )
        self.task = self.plant.task
        self.names = {**self.plant.contract_names(), EFFORT: self.plant.effort_names}

    def _with_effort(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {**obs, EFFORT: self.plant.joint_torques().astype(np.float32)}

    def reset(self, config: TaskConfig) -> dict[str, np.ndarray]:
        return self._with_effort(self.plant.reset(config))

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
        self.plant.act(action)
        assert self.plant.last_joint_target is not None
        return self._with_effort(self.plant.observe()), self.plant.last_joint_target

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
    session: Session | None = None,
    action_noise: float = 0.0,
    on_episode: Callable[[ExpertEpisode], None] | None = None,
    scene: SceneSpec | None = None,
) -> ExpertReport:
    """Run ``episodes`` expert episodes per region in ``world`` (deterministic per seed).

    ``effects`` only applies to the plant (``None``: the built-in plant's hidden effects).
    With a ``session``, every episode is recorded (both cameras): in the twin as
    ``twin_demo`` demonstrations, in the plant as ``teleop`` (the expert stands in for
    the human operator). ``action_noise`` (m) adds human-like jitter to the expert's
    translations (and five times as much, in rad, to its rotations), which the expert
    then corrects like an operator watching the arm. ``scene`` replaces the task's
    built-in cell (e.g. one built by ``twinrl twin build``) in both worlds.
    """
    if world not in WORLDS:
        raise ValueError(f"world must be one of {', '.join(WORLDS)}, got '{world}'")
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    if world == "twin" and effects is not None:
        raise ValueError("effects apply to the plant only; the twin runs its own scene spec")
    spec_task = make_task(task, scene)
    for region in regions:
        spec_task.region(region)
    images = session is not None
    sim = (
        _TwinWorld(task, images, scene)
        if world == "twin"
        else _PlantWorld(task, effects, seed, images, scene)
    )
    rng = np.random.default_rng(seed)
    results = []
    try:
        for r, region in enumerate(regions):
            for i in range(episodes):
                config = sim.task.sample_config(rng, region)
                expert = sim.task.expert(config, np.random.default_rng([seed, r, i]))
                jitter = np.random.default_rng([seed, r, i, 1])
                obs = sim.reset(config)
                log = None
                if session is not None:
                    log = session.record(_episode_meta(sim, config, region))
                steps = 0
                while steps < sim.task.max_steps and not sim.success:
                    action = expert.act(obs)
                    if action_noise > 0:
                        shake = jitter.normal(0.0, action_noise, 6) * [1, 1, 1, 5, 5, 5]
                        action = action.copy()
                        action[:6] += shake
                        expert.perturb(shake[:3], shake[3:])
                    next_obs, joint_target = sim.step(action)
                    steps += 1
                    if log is not None:
                        done = sim.success or steps >= sim.task.max_steps
                        reward = sim.task.reward(Progress(success=sim.success), "sparse")
                        log.append(
                            step_record(obs, action, joint_target, reward, done, sim.success)
                        )
                    obs = next_obs
                if log is not None:
                    log.close()
                episode = ExpertEpisode(region, config.to_dict(), sim.success, steps)
                results.append(episode)
                if on_episode is not None:
                    on_episode(episode)
    finally:
        sim.close()
    return ExpertReport(task=task, world=world, episodes=tuple(results))


def _episode_meta(sim: _TwinWorld | _PlantWorld, config: TaskConfig, region: str) -> EpisodeMeta:
    return EpisodeMeta(
        task=sim.task.name,
        instruction=sim.task.instruction,
        source=sim.source,
        world=sim.world,
        region=region,
        config=config.to_dict(),
        twin=sim.task.scene.digest,
        policy="scripted_expert",
        fps=sim.task.scene.physics.control_hz,
        robot=sim.task.scene.robot.builtin or "custom",
        operator="scripted_expert" if sim.source == "teleop" else None,
        names=sim.names,
    )
