"""twinrl_sim: the MuJoCo twin of a robot cell.

Scene specs, the built-in UR5e cell, the four tasks and their scripted experts,
Gymnasium envs, replay of logged commands, batched simulation and physical effects.
"""

import os

# Headless rendering by default: EGL unless the user chose a backend or has a display.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"

from twinrl_sim.build import CellLayout as CellLayout  # noqa: E402
from twinrl_sim.build import CompiledScene as CompiledScene  # noqa: E402
from twinrl_sim.build import compile_scene as compile_scene  # noqa: E402
from twinrl_sim.cell import Cell as Cell  # noqa: E402
from twinrl_sim.effects import EFFECTS as EFFECTS  # noqa: E402
from twinrl_sim.effects import load_effects as load_effects  # noqa: E402
from twinrl_sim.env import TwinEnv as TwinEnv  # noqa: E402
from twinrl_sim.env import make as make  # noqa: E402
from twinrl_sim.replay import ReplayResult as ReplayResult  # noqa: E402
from twinrl_sim.replay import replay as replay  # noqa: E402
from twinrl_sim.spec import SceneSpec as SceneSpec  # noqa: E402
from twinrl_sim.spec import SpecError as SpecError  # noqa: E402
from twinrl_sim.spec import load_spec as load_spec  # noqa: E402
from twinrl_sim.tasks import TASKS as TASKS  # noqa: E402
from twinrl_sim.tasks import TaskConfig as TaskConfig  # noqa: E402
from twinrl_sim.tasks import make_task as make_task  # noqa: E402
