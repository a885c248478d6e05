"""Run a task's scripted expert in the twin or in the plant and tally success by region."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data.atomic import write_text_atomic
from twinrl_data.recorder import Recorder
from twinrl_data.session import Session
from twinrl_robot.backends import open_robot, recorded_cameras
from twinrl_robot.cell_file import CellFile
from twinrl_robot.errors import RobotError
from twinrl_robot.loop import privileged_success, run_episode
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import REGION_NAMES, Task, TaskConfig, make_task
from twinrl_sim.tasks.expert import ScriptedExpert, stopping_short

# A near miss holds still for this many recorded steps before its episode ends.
NEAR_MISS_HOLD = 5


@dataclass(frozen=True)
class ExpertEpisode:
    region: str
    config: dict[str, list[float]]
    success: bool
    steps: int
    near_miss: bool = False  # the expert stopped short near the goal on purpose


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
        write_text_atomic(
            Path(path),
            json.dumps({**self.to_json(), "runs": [asdict(e) for e in self.episodes]}, indent=1),
        )


class ExpertSource:
    """The task's scripted expert as an action source, with an operator's hand jitter
    of ``noise`` m per step (five times as much, in rad, on rotations), which the
    expert then corrects like a person watching the arm.

    With ``stop_short`` it makes a near miss (:func:`~twinrl_sim.tasks.expert.
    stopping_short`): it goes that fraction of the way through the phase the task's
    ``near_miss`` names and holds still; :meth:`finished` says when it has held for
    ``hold`` steps."""

    def __init__(
        self,
        rng: np.random.Generator,
        jitter: np.random.Generator,
        noise: float,
        stop_short: float | None = None,
        hold: int = NEAR_MISS_HOLD,
    ):
        self.rng, self.jitter, self.noise = rng, jitter, noise
        self.stop_short, self.hold = stop_short, hold
        self.expert: ScriptedExpert | None = None
        self._held = 0

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.expert = task.expert(config, self.rng)
        if self.stop_short is not None:
            self.expert = stopping_short(self.expert, task.near_miss[0], self.stop_short)
        self._held = 0

    def finished(self) -> bool:
        """Whether a near miss has held still long enough to end its episode."""
        return self.stop_short is not None and self._held > self.hold

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        assert self.expert is not None, "reset the source first"
        action = self.expert.act(observation)
        if self.noise > 0:
            shake = self.jitter.normal(0.0, self.noise, 6) * [1, 1, 1, 5, 5, 5]
            action = action.copy()
            action[:6] += shake
            self.expert.perturb(shake[:3], shake[3:])
        self._held += self.expert.done  # the steps it has held still, its phases done
        return action

    def interrupted(self) -> None:
        """Nobody takes the controls from the expert."""


def run_scripted_expert(
    task: str,
    *,
    world: str = "twin",
    episodes: int = 20,
    regions: tuple[str, ...] = REGION_NAMES,
    effects: dict | str | Path | None = None,
    seed: int = 0,
    session: Session | None = None,
    action_noise: float = 0.0,
    on_episode: Callable[[ExpertEpisode], None] | None = None,
    scene: SceneSpec | None = None,
    cell: CellFile | str | Path | None = None,
    emulated: bool = False,
    settle: int = 0,
    near_misses: float = 0.0,
) -> ExpertReport:
    """Run ``episodes`` expert episodes per region in ``world`` (deterministic per seed).

    ``effects`` only applies to the plant (``None``: the built-in plant's hidden effects).
    With a ``session``, every episode is recorded (both cameras): in the twin as
    ``twin_demo`` demonstrations, in the plant as ``teleop`` (the expert stands in for
    the human operator). ``action_noise`` (m) adds human-like jitter to the expert's
    translations (and five times as much, in rad, to its rotations), which the expert
    then corrects like an operator watching the arm. ``scene`` replaces the task's
    built-in cell (e.g. one built by ``twinrl twin build``) in both worlds. ``real`` is
    the arm of ``cell`` (a cell file); the expert reads object poses, which only an
    ``emulated`` cell lends (a real cell refuses it: a person demonstrates there).
    ``settle`` steps are recorded after each success with the arm held (see
    :func:`~twinrl_robot.loop.run_episode`). A share ``near_misses`` of the episodes
    (drawn per episode) are near misses: the expert stops short near the goal and holds
    (:class:`ExpertSource`), recorded with the policy ``scripted_expert:near_miss``; they
    are the hard negatives a reward classifier learns from.
    """
    if episodes < 1:
        raise RobotError(f"episodes must be at least 1, got {episodes}")
    if not 0.0 <= near_misses <= 1.0:
        raise RobotError(f"near_misses is a share of the episodes in [0, 1], got {near_misses}")
    recording = session is not None
    # The expert stands in for a person teleoperating the (stand-in) real cell, whose
    # controller reports joint torques as a UR's does (the gap workflow uses them).
    spec_task = make_task(task, scene)
    for region in regions:
        spec_task.region(region)
    robot = open_robot(
        world,
        spec_task,
        effects=effects,
        seed=seed,
        cameras=recorded_cameras(world, cell) if recording else (),
        effort=world != "twin",
        cell=cell,
        emulated=emulated,
    )
    recorder = Recorder(session) if session is not None else None
    source_name = "twin_demo" if world == "twin" else "teleop"
    rng = np.random.default_rng(seed)
    results = []
    try:
        for r, region in enumerate(regions):
            for i in range(episodes):
                config = spec_task.sample_config(rng, region)
                draw = np.random.default_rng([seed, r, i, 2])
                near_miss = bool(draw.random() < near_misses)
                source = ExpertSource(
                    np.random.default_rng([seed, r, i]),
                    np.random.default_rng([seed, r, i, 1]),
                    action_noise,
                    stop_short=float(draw.uniform(*spec_task.near_miss[1:])) if near_miss else None,
                )
                meta = None
                if recorder is not None:
                    meta = spec_task.episode_meta(
                        source=source_name,
                        world=world,
                        names=robot.names,
                        config=config,
                        region=region,
                        policy="scripted_expert:near_miss" if near_miss else "scripted_expert",
                        operator=None if world == "twin" else "scripted_expert",
                    )
                outcome = run_episode(
                    robot,
                    source,
                    spec_task,
                    config,
                    judge=privileged_success(robot),
                    recorder=recorder,
                    meta=meta,
                    settle=settle,
                    until=source.finished,
                )
                episode = ExpertEpisode(
                    region, config.to_dict(), outcome.success, outcome.steps, near_miss
                )
                results.append(episode)
                if on_episode is not None:
                    on_episode(episode)
    finally:
        robot.close()
    return ExpertReport(task=task, world=world, episodes=tuple(results))
