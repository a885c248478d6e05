"""The task registry: ``make_task(name)`` and the list of built-in tasks."""

from __future__ import annotations

import difflib
from pathlib import Path

from twinrl_data.errors import SettingError
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SPEC_HINT, SceneSpec, SpecError, read_yaml, spec_from_yaml
from twinrl_sim.tasks.base import REGION_NAMES as REGION_NAMES
from twinrl_sim.tasks.base import Progress as Progress
from twinrl_sim.tasks.base import Region as Region
from twinrl_sim.tasks.base import Task as Task
from twinrl_sim.tasks.base import TaskConfig as TaskConfig
from twinrl_sim.tasks.base import Tracker as Tracker
from twinrl_sim.tasks.erase_whiteboard import EraseWhiteboard
from twinrl_sim.tasks.insertion import InsertHexagon, InsertTripleColumn
from twinrl_sim.tasks.pick_place import PickPlace

TASKS: dict[str, type[Task]] = {
    cls.name: cls for cls in (PickPlace, InsertHexagon, InsertTripleColumn, EraseWhiteboard)
}


def task_class(name: str) -> type[Task]:
    """The task class called ``name``; the error suggests the nearest task name."""
    if name not in TASKS:
        close = difflib.get_close_matches(name, list(TASKS), n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise TwinError(f"unknown task '{name}'{hint}; tasks: {', '.join(TASKS)}")
    return TASKS[name]


def make_task(name: str, scene: SceneSpec | None = None) -> Task:
    """Instantiate task ``name`` on its built-in scene or on ``scene``."""
    return task_class(name)(scene)


def twin_scene(twin: str) -> SceneSpec:
    """The scene spec named by ``twin``: a built-in task's cell (``pick_place``), a scene
    spec YAML file, or a real cell's file (:mod:`twinrl_robot.cell_file`: ``arm`` and
    ``twin`` keys), whose twin is taken as its arm runs it: servos that track their
    targets and feed the arm's model forward, as a UR's controller does."""
    if twin in TASKS:
        return make_task(twin).scene
    path = Path(twin)
    if path.suffix in (".yaml", ".yml") or path.exists():
        data = read_yaml(path, "scene spec", SpecError, SPEC_HINT)
        if isinstance(data, dict) and {"arm", "twin"} <= set(data):
            named = str(data["twin"])
            scene = twin_scene(named if named in TASKS else str(path.parent / named))
            physics = scene.physics.model_copy(update={"servo": "track"})
            return scene.model_copy(update={"physics": physics})
        return spec_from_yaml(data, path)
    close = difflib.get_close_matches(twin, list(TASKS), n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    raise SettingError(
        "twin",
        f"'{twin}' is neither a built-in cell{hint} ({', '.join(TASKS)}) nor a scene spec file",
    )


def task_on_twin(task: str, twin: str) -> SceneSpec:
    """The cell named by ``twin``, checked to hold ``task``'s objects."""
    scene = twin_scene(twin)
    try:
        make_task(task, scene)
    except SpecError as err:
        raise SettingError(
            "twin", f"{twin}: {err.args[0]}; pick the `task` it is built for"
        ) from None
    return scene
