"""How a teleop device's axes and buttons become the episode's 7-D action and a
person's marks: the ``teleop`` section of a cell file.

::

    teleop:
      spacemouse:
        translation: 0.02        # m per control step at full deflection
        rotation: 0.1            # rad per control step at full deflection
        deadband: 0.1            # fraction of full deflection ignored (the cap's rest)
        axes: [y, -x, z, pitch, -roll, yaw]   # device axis per action axis x y z rx ry rz
        buttons: {gripper: LEFT, takeover: RIGHT}
      gamepad:
        deadman: BTN_TL          # held for motion; released, the arm holds
        buttons: {gripper: BTN_SOUTH, takeover: BTN_TR, success: BTN_NORTH, ...}

Each device kind has defaults (:data:`DEFAULT_MAPS`); a cell file overrides any field.
An action axis maps to one device axis, ``-`` in front reverses it, ``none`` leaves
the action axis still: turn the map to where the person stands. ``buttons`` maps each
:data:`EVENTS` name to the device's button (or key) that raises it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

ACTION_AXES = ("x", "y", "z", "rx", "ry", "rz")  # the action's motion, base frame
EVENTS = ("start", "success", "failure", "discard", "note", "quit", "gripper", "takeover")
"""What a person's button or key can say: start an episode (the cell is set up), mark it
a success, a failure, or discarded (record it again), type a note, stop the session,
toggle the gripper, take the controls from the policy or hand them back."""
DEVICE_AXES = {
    "spacemouse": ("x", "y", "z", "roll", "pitch", "yaw"),
    "gamepad": (
        "ABS_X",
        "ABS_Y",
        "ABS_RX",
        "ABS_RY",
        "ABS_Z",
        "ABS_RZ",
        "ABS_HAT0X",
        "ABS_HAT0Y",
    ),
    "keyboard": ("x", "y", "z", "rx", "ry", "rz"),
    "scripted": ("x", "y", "z", "rx", "ry", "rz"),
}


class DeviceMap(BaseModel):
    """One device kind's scaling, deadband, axis map, deadman and buttons."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    translation: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=0.1)] = 0.02
    rotation: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=0.5)] = 0.1
    deadband: Annotated[float, Field(allow_inf_nan=False, ge=0.0, lt=1.0)] = 0.1
    axes: tuple[str, str, str, str, str, str] = ("x", "y", "z", "rx", "ry", "rz")
    deadman: str | None = None
    buttons: dict[str, str] = {}

    @model_validator(mode="after")
    def _events(self) -> DeviceMap:
        unknown = sorted(set(self.buttons) - set(EVENTS))
        if unknown:
            raise ValueError(f"unknown event(s) {unknown} in buttons; events: {', '.join(EVENTS)}")
        return self

    def check_axes(self, kind: str) -> None:
        """Refuse axis names the device kind does not have, in one line."""
        known = DEVICE_AXES[kind]
        for action_axis, spec in zip(ACTION_AXES, self.axes, strict=True):
            name = spec.removeprefix("-")
            if name != "none" and name not in known:
                raise ValueError(
                    f"axes: action axis {action_axis} maps to unknown device axis "
                    f"'{spec}'; a {kind} has {', '.join(known)} (or none)"
                )


DEFAULT_MAPS: dict[str, DeviceMap] = {
    # pyspacemouse's right-handed Z-up frame: push the cap away to move +y, lift for +z.
    "spacemouse": DeviceMap(
        axes=("x", "y", "z", "roll", "pitch", "yaw"),
        buttons={"gripper": "LEFT", "takeover": "RIGHT"},
    ),
    # An Xbox-style pad: left stick x/y, right stick up/down z and left/right yaw, the
    # D-pad tilts; hold the left bumper to move.
    "gamepad": DeviceMap(
        axes=("-ABS_Y", "-ABS_X", "-ABS_RY", "ABS_HAT0X", "-ABS_HAT0Y", "-ABS_RX"),
        deadband=0.15,
        deadman="BTN_TL",
        buttons={
            "gripper": "BTN_SOUTH",
            "takeover": "BTN_TR",
            "success": "BTN_NORTH",
            "failure": "BTN_EAST",
            "discard": "BTN_WEST",
            "start": "BTN_START",
        },
    ),
    # Keys in the terminal (see teleop.terminal): motion keys give full deflection.
    "keyboard": DeviceMap(
        deadband=0.0, translation=0.01, rotation=0.05, buttons={"gripper": "space", "takeover": "t"}
    ),
    # The scripted person (plant and emulator): its device reports the expert's motion.
    "scripted": DeviceMap(
        deadband=0.0, translation=0.05, rotation=0.5, buttons={e: e for e in EVENTS}
    ),
}


class TeleopSpec(BaseModel):
    """The cell file's ``teleop`` section: per device kind, what differs from the defaults."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    spacemouse: dict = {}
    gamepad: dict = {}
    keyboard: dict = {}

    @model_validator(mode="after")
    def _valid_maps(self) -> TeleopSpec:
        for kind in ("spacemouse", "gamepad", "keyboard"):
            try:
                self.device_map(kind)
            except ValidationError as err:
                problems = "; ".join(
                    ".".join([kind, *map(str, e["loc"])])
                    + ": "
                    + e["msg"].removeprefix("Value error, ")
                    for e in err.errors()
                )
                raise ValueError(problems) from None
            except ValueError as err:
                raise ValueError(f"{kind}.{err}") from None
        return self

    def device_map(self, kind: str) -> DeviceMap:
        """The map of device ``kind``: its defaults with this cell's changes."""
        overrides = getattr(self, kind, {}) if kind != "scripted" else {}
        merged = DEFAULT_MAPS[kind].model_dump() | dict(overrides)
        device_map = DeviceMap.model_validate(merged)
        device_map.check_axes(kind)
        return device_map
