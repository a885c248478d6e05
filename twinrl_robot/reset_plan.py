"""Where each recorded episode starts: a plan of task configurations.

``--plan`` is a region (``ID`` or ``OOD``: configurations sampled from it, seeded), or a
JSON file: the ``targets.json`` that ``twinrl mine`` writes (its reset targets in rank
order, each with its region), or a plain list of configurations
(``[{"object": [x, y, yaw], "target": [x, y, yaw]}, ...]``). A list is gone through in
order and starts over when the session records more episodes than it holds.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinrl_data.errors import DataError, SettingError
from twinrl_sim.tasks import REGION_NAMES, Task, TaskConfig


@dataclass(frozen=True)
class PlannedReset:
    config: TaskConfig
    region: str | None


class ResetPlan:
    """The configurations a session's episodes start from, in order."""

    def __init__(self, task: Task, plan: str | None, *, seed: int = 0) -> None:
        self.task, self.description = task, plan or "ID"
        self._rng = np.random.default_rng(seed)
        self._listed: list[PlannedReset] = []
        self._drawn: list[PlannedReset] = []
        self._region: str | None = None
        if plan is None or plan in REGION_NAMES:
            self._region = plan or "ID"
            task.region(self._region)
        elif plan.endswith(".json"):
            self._listed = _read_list(Path(plan), task)
        else:
            raise SettingError(
                "plan", f"'{plan}' is neither a region ({', '.join(REGION_NAMES)}) nor a .json file"
            )

    def reset(self, index: int) -> PlannedReset:
        """The ``index``-th episode's start: the same for the same index (an episode
        recorded again), a region's samples drawn in order, seeded."""
        if self._listed:
            return self._listed[index % len(self._listed)]
        while len(self._drawn) <= index:
            config = self.task.sample_config(self._rng, self._region)
            self._drawn.append(PlannedReset(config, self._region))
        return self._drawn[index]


def _read_list(path: Path, task: Task) -> list[PlannedReset]:
    if not path.is_file():
        raise DataError(
            f"plan file {path} does not exist; give a targets.json or a list of configs"
        )
    try:
        data = json.loads(path.read_text())
        items = data["targets"] if isinstance(data, dict) else data
        resets = []
        for item in items:
            if "config" in item:
                resets.append(
                    PlannedReset(TaskConfig.from_dict(item["config"]), item.get("region"))
                )
            else:
                config = TaskConfig.from_dict(item)
                resets.append(PlannedReset(config, task.region_of(config)))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise DataError(
            f"{path} is neither a targets.json from `twinrl mine` nor a list of configurations "
            f"({err})"
        ) from None
    if not resets:
        raise DataError(f"plan file {path} lists no configurations")
    return resets
