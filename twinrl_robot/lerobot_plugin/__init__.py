"""A twinrl UR cell and twinrl's teleop devices in LeRobot's own tools.

Loaded by lerobot's plugin mechanism: its commands import the package named by
``--robot.discover_packages_path`` / ``--teleop.discover_packages_path`` (and every
module in it), which registers the configs here with lerobot's registries::

    lerobot-record \\
        --robot.discover_packages_path=twinrl_robot.lerobot_plugin \\
        --robot.type=twinrl_ur --robot.cell=lab_ur5e.yaml \\
        --teleop.discover_packages_path=twinrl_robot.lerobot_plugin \\
        --teleop.type=twinrl_spacemouse --teleop.cell=lab_ur5e.yaml \\
        --dataset.repo_id=me/ur_demos --dataset.fps=10 --dataset.single_task="..."

lerobot finds each device class beside its config (``TwinrlURConfig`` -> ``TwinrlUR``),
so both are exported here. See the guide ``docs/guides/lerobot-tools.md``.
"""

from twinrl_robot.lerobot_plugin.config import (
    TwinrlGamepadConfig,
    TwinrlSpaceMouseConfig,
    TwinrlURConfig,
)
from twinrl_robot.lerobot_plugin.robot import TwinrlUR
from twinrl_robot.lerobot_plugin.teleoperator import TwinrlGamepad, TwinrlSpaceMouse

__all__ = [
    "TwinrlGamepad",
    "TwinrlGamepadConfig",
    "TwinrlSpaceMouse",
    "TwinrlSpaceMouseConfig",
    "TwinrlUR",
    "TwinrlURConfig",
]
