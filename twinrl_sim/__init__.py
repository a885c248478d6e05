"""twinrl_sim: the MuJoCo twin of a robot cell.

Scene specs, the built-in UR5e cell, the four tasks and their scripted experts,
Gymnasium envs, replay of logged commands, batched simulation and physical effects.
"""

import os

# Headless rendering by default: EGL unless the user chose a backend or has a display.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"

from twinrl_sim.batch import BatchEnv as BatchEnv
from twinrl_sim.batch import BatchRollout as BatchRollout
from twinrl_sim.build import CellLayout as CellLayout
from twinrl_sim.build import CompiledScene as CompiledScene
from twinrl_sim.build import compile_scene as compile_scene
from twinrl_sim.cell import Cell as Cell
from twinrl_sim.effects import EFFECTS as EFFECTS
from twinrl_sim.effects import load_effects as load_effects
from twinrl_sim.env import TwinEnv as TwinEnv
from twinrl_sim.env import make as make
from twinrl_sim.env import register_envs as register_envs
from twinrl_sim.replay import ReplayResult as ReplayResult
from twinrl_sim.replay import replay as replay
from twinrl_sim.spec import SceneSpec as SceneSpec
from twinrl_sim.spec import SpecError as SpecError
from twinrl_sim.spec import load_spec as load_spec
from twinrl_sim.tasks import TASKS as TASKS
from twinrl_sim.tasks import TaskConfig as TaskConfig
from twinrl_sim.tasks import make_task as make_task

register_envs()
