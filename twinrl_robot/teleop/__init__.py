"""Teleop devices: a person's hand on the arm (SpaceMouse, gamepad, keyboard), and a
scripted person for cells without one. See :func:`open_teleop`."""

from __future__ import annotations

from collections.abc import Sequence

from twinrl_robot.operator import OperatorRule
from twinrl_robot.robot import Privileged
from twinrl_robot.teleop.device import InputDevice, TeleopError
from twinrl_robot.teleop.settings import TeleopSpec
from twinrl_robot.teleop.teleop import Teleop
from twinrl_robot.teleop.terminal import TerminalKeys

TELEOP_KINDS = ("spacemouse", "gamepad", "keyboard", "scripted")


def open_teleop(
    kind: str,
    spec: TeleopSpec | None = None,
    *,
    terminal: TerminalKeys | None = None,
    privileged: Privileged | None = None,
    seed: int = 0,
    marks: Sequence[str] = (),
    watch: OperatorRule | None = None,
) -> Teleop:
    """Open a teleop device and its map from the cell file's ``teleop`` section.

    ``kind``: ``spacemouse`` (the first one plugged in), ``gamepad`` or
    ``gamepad:/dev/input/eventN`` (evdev), ``gamepad:sdl`` (SDL's controller layout,
    through pygame), ``keyboard`` (the ``terminal``'s keys), ``scripted``
    (the task's expert at a virtual device; needs the cell's ``privileged`` ground
    truth, and presses ``marks`` in turn at each episode's end; in real RL it ``watch``es
    the policy and takes over as that rule says).
    """
    spec = spec or TeleopSpec()
    name, _, where = kind.partition(":")
    device: InputDevice
    if name == "spacemouse":
        from twinrl_robot.teleop.spacemouse import open_spacemouse

        device = open_spacemouse()
    elif name == "gamepad" and where == "sdl":
        from twinrl_robot.teleop.gamepad_sdl import open_sdl_gamepad

        device = open_sdl_gamepad()
    elif name == "gamepad":
        from twinrl_robot.teleop.gamepad import open_gamepad

        device = open_gamepad(where or None)
    elif name == "keyboard":
        from twinrl_robot.teleop.terminal import Keyboard

        if terminal is None:
            raise TeleopError(
                "the keyboard device reads the terminal's keys; run in a terminal, or choose "
                "another `teleop`"
            )
        device = Keyboard(terminal)
    elif name == "scripted":
        from twinrl_robot.teleop.scripted import ScriptedPerson

        device = ScriptedPerson(
            privileged, spec.device_map("scripted"), marks=marks, seed=seed, watch=watch
        )
    else:
        raise TeleopError(f"unknown teleop device '{kind}'; use one of {', '.join(TELEOP_KINDS)}")
    return Teleop(device, spec.device_map(name))


__all__ = ["TELEOP_KINDS", "Teleop", "TeleopError", "TerminalKeys", "open_teleop"]
