"""twinrl_sim: the MuJoCo twin of a robot cell.

Scene specs, the built-in UR5e cell, the four tasks and their scripted experts,
Gymnasium envs, replay of logged commands, batched simulation and physical effects.

The names below load on first use, so that importing one submodule (the command line
does, to list its commands) loads only what that submodule needs.
"""

import importlib
import os
from typing import Any

import gymnasium as gym

# Headless rendering by default: EGL unless the user chose a backend or has a display.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"

_EXPORTS = {
    "BatchEnv": "twinrl_sim.batch",
    "BatchRollout": "twinrl_sim.batch",
    "CellLayout": "twinrl_sim.layout",
    "CompiledScene": "twinrl_sim.build",
    "compile_scene": "twinrl_sim.build",
    "Cell": "twinrl_sim.cell",
    "EFFECTS": "twinrl_sim.effects",
    "load_effects": "twinrl_sim.effects",
    "TwinEnv": "twinrl_sim.env",
    "make": "twinrl_sim.env",
    "ReplayResult": "twinrl_sim.replay",
    "replay": "twinrl_sim.replay",
    "SceneSpec": "twinrl_sim.spec",
    "SpecError": "twinrl_sim.spec",
    "load_spec": "twinrl_sim.spec",
    "TASKS": "twinrl_sim.tasks",
    "TaskConfig": "twinrl_sim.tasks",
    "make_task": "twinrl_sim.tasks",
}

# Gymnasium ids of the tasks (``gymnasium.make("twinrl/PickPlace-v0")``).
GYM_IDS = {
    "pick_place": "twinrl/PickPlace-v0",
    "insert_hexagon": "twinrl/InsertHexagon-v0",
    "insert_triple_column": "twinrl/InsertTripleColumn-v0",
    "erase_whiteboard": "twinrl/EraseWhiteboard-v0",
}


def register_envs() -> None:
    """Register every task with Gymnasium; the env module loads when one is made."""
    for task, env_id in GYM_IDS.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="twinrl_sim.env:TwinEnv", kwargs={"task": task})


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'twinrl_sim' has no attribute '{name}'")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


register_envs()
