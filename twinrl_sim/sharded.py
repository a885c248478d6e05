"""Twin environments split into shards, one :class:`~twinrl_sim.batch.BatchEnv` per
worker of an executor (worker processes here, or Ray actors on a cluster).

:class:`ShardedBatchEnv` has :class:`~twinrl_sim.batch.BatchEnv`'s API. The policy that
acts stays with the caller: every step sends each shard its envs' actions and gathers
their observations, rewards and ends, in env order. Each env steps exactly as it would
alone (a BatchEnv's envs never share state), so a seeded run gives the same results
with any number of shards, on any machines; the caller's learner is untouched, where
sending it weights once per round would change what each step was acted with.

    env = ShardedBatchEnv("pick_place", 16, executor)   # doctest: +SKIP
"""

from __future__ import annotations

from typing import Any

import numpy as np

from twinrl_data.executor import Executor
from twinrl_sim.batch import BatchEnv
from twinrl_sim.errors import TwinError
from twinrl_sim.tasks import Task, TaskConfig, make_task


class ShardedBatchEnv:
    """``num_envs`` twin envs in at most ``executor.workers`` shards (as even as can be);
    see the module docstring. ``effects``, ``reward`` and ``cameras`` as BatchEnv's."""

    def __init__(
        self,
        task: str | Task,
        num_envs: int,
        executor: Executor,
        *,
        effects: dict | None = None,
        reward: str = "sparse",
        cameras: tuple[str, ...] = (),
    ) -> None:
        if num_envs < 1:
            raise TwinError(f"num_envs must be at least 1, got {num_envs}")
        self.task = make_task(task) if isinstance(task, str) else task
        self.num_envs = num_envs
        shards = min(executor.workers, num_envs)
        sizes = [num_envs // shards + (i < num_envs % shards) for i in range(shards)]
        self._bounds = np.cumsum([0, *sizes])
        self._shards = executor.actors(
            BatchEnv,
            [
                # One thread per shard: a worker is one CPU's.
                dict(task=self.task, num_envs=n, effects=effects, reward=reward, nthread=1,
                     cameras=tuple(cameras))
                for n in sizes
            ],
        )  # fmt: skip
        self.cameras = tuple(cameras)

    @property
    def shards(self) -> int:
        return len(self._bounds) - 1

    def _split(self, rows: Any) -> list[tuple]:
        return [(rows[a:b],) for a, b in zip(self._bounds[:-1], self._bounds[1:], strict=True)]

    def contract_names(self) -> dict[str, list[str]]:
        """The episode contract's ``names`` (every shard's are the same)."""
        return self._shards.call("contract_names", [()] * self.shards)[0]

    def reset(self, configs: list[TaskConfig | dict]) -> dict[str, np.ndarray]:
        if len(configs) != self.num_envs:
            raise TwinError(f"reset needs {self.num_envs} configs, got {len(configs)}")
        return _joined(self._shards.call("reset", self._split(list(configs))))

    def step(
        self, actions: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        actions = np.asarray(actions)
        if actions.ndim != 2 or len(actions) != self.num_envs:
            raise TwinError(
                f"actions must have one row per env ({self.num_envs}), got shape {actions.shape}"
            )
        parts = self._shards.call("step", self._split(actions))
        obs, rewards, terminated, truncated, info = zip(*parts, strict=True)
        return (
            _joined(obs),
            np.concatenate(rewards),
            np.concatenate(terminated),
            np.concatenate(truncated),
            _joined(info),
        )

    def close(self) -> None:
        self._shards.close()


def _joined(parts: Any) -> dict[str, np.ndarray]:
    """Per key, the shards' arrays in env order."""
    return {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
