"""The plugin's configs, registered with lerobot's own registries so that its commands
take ``--robot.type=twinrl_ur`` and ``--teleop.type=twinrl_spacemouse|twinrl_gamepad``.

Each config checks what it names (the cell file, its task and cameras, a recording) when
lerobot parses the command line, and refuses bad input as a
:class:`draccus.utils.DecodingError`: lerobot's parser prints that as one line
(``error: ...``) and exits with status 1, where any other exception would end the command
with a traceback.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from draccus.utils import DecodingError
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig

from twinrl_data.errors import TwinrlError
from twinrl_robot.cell_file import CameraSpec, CellFile, load_cell
from twinrl_robot.teleop.settings import DeviceMap, TeleopSpec
from twinrl_sim.tasks import TASKS, Task, make_task, task_on_twin


@dataclass(frozen=True)
class OpenedCell:
    """What a :class:`TwinrlURConfig` names: the cell file, the task on its twin and the
    cameras read."""

    cell: CellFile
    task: Task
    cameras: tuple[CameraSpec, ...]


@RobotConfig.register_subclass("twinrl_ur")
@dataclass(kw_only=True)
class TwinrlURConfig(RobotConfig):
    """A twinrl UR cell, opened from its cell file through twinrl's own backend (each
    field's comment is its ``--help``)."""

    # The cell file: arm, gripper, cameras, safety limits, teleop settings.
    cell: Path
    # The task on the cell's twin; it sets the start pose the arm goes to. None: the
    # twin's own, when it is a built-in cell such as pick_place.
    task: str | None = None
    # The cell file's cameras to read, e.g. [front]. None: all of them.
    cameras: list[str] | None = None
    # The cell is `twinrl robot emulate`'s: at connection its harness places the task's
    # objects in a sampled configuration, as a person does at a real cell.
    emulated: bool = False

    def __post_init__(self) -> None:
        # RobotConfig's own check reads `cameras` as lerobot camera configs; these are
        # the cell file's camera names, checked here instead.
        try:
            self.open()
        except TwinrlError as err:
            raise DecodingError((), f"--robot: {err}") from None

    def open(self) -> OpenedCell:
        """The cell file, the task and the cameras, or a :class:`TwinrlError` in one line."""
        cell = load_cell(self.cell)
        if self.task is None and cell.twin not in TASKS:
            raise TwinrlError(
                f"the twin of {self.cell} is a scene spec; name the task on it with "
                f"--robot.task ({', '.join(TASKS)})"
            )
        name = self.task or cell.twin
        task = make_task(name, task_on_twin(name, cell.twin))
        known = {camera.name: camera for camera in cell.cameras}
        wanted = list(known) if self.cameras is None else self.cameras
        unknown = [name for name in wanted if name not in known]
        if unknown:
            raise TwinrlError(
                f"camera(s) {', '.join(unknown)} are not in the cell file {self.cell}, which has "
                f"{', '.join(known) or 'none'}"
            )
        return OpenedCell(cell, task, tuple(known[name] for name in wanted))


@dataclass(kw_only=True)
class TwinrlTeleopConfig(TeleoperatorConfig):
    """What every twinrl teleop device takes (each field's comment is its ``--help``)."""

    # A cell file whose teleop section maps the device: scaling, deadband, axes,
    # buttons. None: the device's built-in map.
    cell: Path | None = None
    # A recording played back in real time instead of the device (a virtual device).
    recorded: Path | None = None
    kind: ClassVar[str]  # the device kind of twinrl's teleop settings

    def __post_init__(self) -> None:
        try:
            self.device_map()
        except TwinrlError as err:
            raise DecodingError((), f"--teleop: {err}") from None
        if self.recorded is not None and not self.recorded.is_file():
            raise DecodingError((), f"--teleop.recorded: {self.recorded} does not exist")

    def device_map(self) -> DeviceMap:
        """The device's map: the cell file's ``teleop`` settings, or the defaults."""
        spec = load_cell(self.cell).teleop if self.cell is not None else TeleopSpec()
        return spec.device_map(self.kind)


@TeleoperatorConfig.register_subclass("twinrl_spacemouse")
@dataclass(kw_only=True)
class TwinrlSpaceMouseConfig(TwinrlTeleopConfig):
    """A 3Dconnexion SpaceMouse, the first plugged in; ``recorded``: a report recording
    (:meth:`twinrl_robot.teleop.spacemouse.RecordedReports.load`)."""

    kind = "spacemouse"


@TeleoperatorConfig.register_subclass("twinrl_gamepad")
@dataclass(kw_only=True)
class TwinrlGamepadConfig(TwinrlTeleopConfig):
    """A gamepad; ``recorded``: an evdev event recording
    (:func:`twinrl_robot.lerobot_plugin.teleoperator.load_gamepad_events`)."""

    # Which pad: "" (the first evdev pad), /dev/input/eventN, or sdl (SDL's controller
    # layout, through pygame).
    device: str = ""
    kind = "gamepad"
