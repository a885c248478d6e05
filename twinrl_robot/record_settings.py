"""What ``twinrl record`` runs: one settings record, from which its options derive."""

from __future__ import annotations

from dataclasses import dataclass, fields

from twinrl_data.errors import SettingError
from twinrl_sim.tasks import task_class

RECORDING_ROBOTS = ("plant", "ur")


@dataclass(frozen=True)
class RecordSettings:
    """A recording session: ``episodes`` kept episodes of ``task`` into ``out``."""

    out: str
    """Session folder (created, or continued when it exists)."""
    task: str = "pick_place"
    """Task (pick_place, insert_hexagon, insert_triple_column, erase_whiteboard)."""
    robot: str = "plant"
    """Robot to record on: plant, or ur (the UR arm of `cell`)."""
    cell: str | None = None
    """The UR cell's file (robot ur), see 'twinrl cell check'."""
    emulated: bool = False
    """The UR cell is the emulator (`twinrl robot emulate`): it sets each configuration up
    and lends the plant's ground truth (object poses, success), which a real cell lacks."""
    teleop: str = "spacemouse"
    """The person's device: spacemouse, gamepad (or gamepad:/dev/input/eventN; gamepad:sdl
    for SDL's controller layout), keyboard, or scripted (the task's expert at a virtual
    device: plant and emulator only)."""
    episodes: int = 10
    """Episodes to keep (discarded ones are redone)."""
    plan: str | None = None
    """Where episodes start: ID or OOD (sampled), a targets.json from 'twinrl mine', or a
    JSON list of configurations. Default: ID."""
    viewer: bool = False
    """Spawn a Rerun viewer with the live view."""
    connect: str | None = None
    """Send the live view to a running Rerun viewer at this URL."""
    save_view: str | None = None
    """Save the live view to this .rrd file."""
    web: bool = False
    """Serve the live view to browsers with Rerun's web viewer (a machine without a
    screen): its page's address is printed."""
    bind: str = "127.0.0.1"
    """Address the web viewer listens on (default: this machine only)."""
    web_port: int = 9090
    """Port of the web viewer's page."""
    grpc_port: int = 9876
    """Port the web viewer's page reads the live view from."""
    keys: bool = True
    """Read the marks' keys from the terminal (when it is one)."""
    effects: str | None = None
    """The plant's hidden effects (YAML; default: the built-in plant)."""
    settle: int = 3
    """Steps recorded after a success mark with the arm held still, so the last frames
    show the success (what 'twinrl train reward-classifier' learns from)."""
    max_steps: int | None = None
    """Steps before an episode ends as a failure (default: the task's)."""
    seed: int = 0
    """Seed of sampled configurations."""
    marks: tuple[str, ...] = ()
    """The scripted person's marks, in order (success, failure, discard; teleop scripted)."""

    def __post_init__(self) -> None:
        task_class(self.task)  # an unknown task: the nearest name
        if self.robot not in RECORDING_ROBOTS:
            raise SettingError(
                "robot", f"'{self.robot}' is unknown; record on plant or ur (with its `cell`)"
            )
        if self.robot == "ur" and self.cell is None:
            raise SettingError("cell", "is missing: recording on a UR arm needs its cell file")
        if self.robot == "plant" and self.cell is not None:
            raise SettingError("cell", "describes a UR arm; record on it with `robot` ur")
        if self.robot == "plant" and self.emulated:
            raise SettingError(
                "emulated", "names a UR cell's emulator; record on it with `robot` ur"
            )
        if self.robot == "ur" and self.effects is not None:
            raise SettingError("effects", "apply to the plant only; a UR cell has its own physics")
        for name, least in (("episodes", 1), ("settle", 0), ("max_steps", 1)):
            value = getattr(self, name)
            if value is not None and value < least:
                raise SettingError(name, f"must be at least {least}, got {value}")
        given = [n for n in ("viewer", "connect", "save_view", "web") if getattr(self, n)]
        if len(given) > 1:
            raise SettingError(
                given[1], f"goes with `{given[0]}`; the live view goes to one of them"
            )
        if self.save_view is not None and not self.save_view.endswith(".rrd"):
            raise SettingError("save_view", f"must name a .rrd file, got {self.save_view}")
        defaults = {f.name: f.default for f in fields(self)}
        for name in ("bind", "web_port", "grpc_port"):
            if not self.web and getattr(self, name) != defaults[name]:
                raise SettingError(name, "goes with `web`: it is where the web viewer listens")
        for name in ("web_port", "grpc_port"):
            if not 0 < getattr(self, name) < 65536:
                raise SettingError(name, f"must be a port, 1 to 65535, got {getattr(self, name)}")

    @property
    def view(self) -> str | None:
        """Where the live view goes: ``spawn``, a viewer's URL, an ``.rrd`` path, or nowhere."""
        if self.viewer:
            return "spawn"
        return self.connect or self.save_view
