"""A gamepad through SDL's game-controller layer (``pygame``, the ``sdl`` extra).

SDL's controller database gives every pad it knows the same layout by position, which
the kernel's own button names do not (an Xbox pad's left face button is ``BTN_X``, that
is ``BTN_NORTH``, while a PlayStation pad's is ``BTN_WEST``); and where there is no
evdev (macOS, Windows) it is the way in. No window is opened: SDL runs with its dummy
video driver unless one is set, and lets pad events through without a focused window.

The pad's controls are reported under the evdev names the ``gamepad`` map uses, so one
map serves both: sticks ``ABS_X``/``ABS_Y`` and ``ABS_RX``/``ABS_RY``, triggers
``ABS_Z``/``ABS_RZ``, the D-pad as the hat ``ABS_HAT0X``/``ABS_HAT0Y``, the face
buttons by where they sit (bottom ``BTN_SOUTH``, right ``BTN_EAST``, top
``BTN_NORTH``, left ``BTN_WEST``), bumpers ``BTN_TL``/``BTN_TR``, ``BTN_SELECT``,
``BTN_START``, ``BTN_MODE``, ``BTN_THUMBL``/``BTN_THUMBR``.
"""

from __future__ import annotations

import functools
import os
import time
import warnings
from typing import Any

from evdev import ecodes

from twinrl_robot.teleop.device import TeleopError
from twinrl_robot.teleop.gamepad import Gamepad

STICK = (-32768, 32767)  # SDL's axis range; triggers use its upper half
TRIGGER = (0, 32767)
POLL_INTERVAL = 0.005  # s between looks at SDL's queue while waiting for events


@functools.cache
def _sdl() -> Any:
    """pygame with SDL's video (dummy unless set), joystick and controller parts up
    (once: the finder and every pad's source share them)."""
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    os.environ.setdefault("SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS", "1")
    try:
        with warnings.catch_warnings():  # pygame's own packaging warns on import
            warnings.simplefilter("ignore")
            import pygame
            from pygame._sdl2 import controller
    except ImportError:
        raise TeleopError(
            "the SDL gamepad needs pygame: pip install 'twinrl[sdl]', or use `gamepad` "
            "(evdev) on Linux"
        ) from None
    pygame.display.init()  # SDL's event queue lives with its video part
    pygame.joystick.init()
    controller.init()
    return pygame


class SdlSource:
    """One SDL game controller's events, as the ``(type, code, value)`` triples of
    :class:`~twinrl_robot.teleop.gamepad.EventSource`."""

    def __init__(self, instance_id: int, name: str, handle: Any = None) -> None:
        self._pygame = pygame = _sdl()
        self.instance_id, self.name, self._handle = instance_id, name, handle
        self._axes = {
            pygame.CONTROLLER_AXIS_LEFTX: ecodes.ABS_X,
            pygame.CONTROLLER_AXIS_LEFTY: ecodes.ABS_Y,
            pygame.CONTROLLER_AXIS_RIGHTX: ecodes.ABS_RX,
            pygame.CONTROLLER_AXIS_RIGHTY: ecodes.ABS_RY,
            pygame.CONTROLLER_AXIS_TRIGGERLEFT: ecodes.ABS_Z,
            pygame.CONTROLLER_AXIS_TRIGGERRIGHT: ecodes.ABS_RZ,
        }
        self._buttons = {
            pygame.CONTROLLER_BUTTON_A: ecodes.BTN_SOUTH,
            pygame.CONTROLLER_BUTTON_B: ecodes.BTN_EAST,
            pygame.CONTROLLER_BUTTON_Y: ecodes.BTN_NORTH,
            pygame.CONTROLLER_BUTTON_X: ecodes.BTN_WEST,
            pygame.CONTROLLER_BUTTON_LEFTSHOULDER: ecodes.BTN_TL,
            pygame.CONTROLLER_BUTTON_RIGHTSHOULDER: ecodes.BTN_TR,
            pygame.CONTROLLER_BUTTON_BACK: ecodes.BTN_SELECT,
            pygame.CONTROLLER_BUTTON_START: ecodes.BTN_START,
            pygame.CONTROLLER_BUTTON_GUIDE: ecodes.BTN_MODE,
            pygame.CONTROLLER_BUTTON_LEFTSTICK: ecodes.BTN_THUMBL,
            pygame.CONTROLLER_BUTTON_RIGHTSTICK: ecodes.BTN_THUMBR,
        }
        # The D-pad's buttons, as the hat axis and direction each one pushes.
        self._dpad = {
            pygame.CONTROLLER_BUTTON_DPAD_LEFT: (ecodes.ABS_HAT0X, -1),
            pygame.CONTROLLER_BUTTON_DPAD_RIGHT: (ecodes.ABS_HAT0X, 1),
            pygame.CONTROLLER_BUTTON_DPAD_UP: (ecodes.ABS_HAT0Y, -1),
            pygame.CONTROLLER_BUTTON_DPAD_DOWN: (ecodes.ABS_HAT0Y, 1),
        }
        self._held_dpad: set[int] = set()
        self._kinds = (
            pygame.CONTROLLERAXISMOTION,
            pygame.CONTROLLERBUTTONDOWN,
            pygame.CONTROLLERBUTTONUP,
            pygame.CONTROLLERDEVICEREMOVED,
        )

    def read_events(self, timeout: float) -> list[tuple[int, int, int]]:
        """What the pad did since the last call, waiting up to ``timeout`` for
        something; raises ``OSError`` once the pad is gone."""
        deadline = time.monotonic() + timeout
        while True:
            out = []
            for event in self._pygame.event.get(self._kinds):
                out += self._translate(event)
            if out or time.monotonic() >= deadline:
                return out
            time.sleep(POLL_INTERVAL)

    def _translate(self, event: Any) -> list[tuple[int, int, int]]:
        pygame = self._pygame
        if getattr(event, "instance_id", None) != self.instance_id:
            return []  # another pad's
        if event.type == pygame.CONTROLLERDEVICEREMOVED:
            raise OSError(19, "No such device")
        if event.type == pygame.CONTROLLERAXISMOTION:
            code = self._axes.get(event.axis)
            return [] if code is None else [(ecodes.EV_ABS, code, int(event.value))]
        pressed = event.type == pygame.CONTROLLERBUTTONDOWN
        if event.button in self._dpad:
            (self._held_dpad.add if pressed else self._held_dpad.discard)(event.button)
            code, _ = self._dpad[event.button]
            value = sum(d for b, (c, d) in self._dpad.items() if c == code and b in self._held_dpad)
            return [(ecodes.EV_ABS, code, value)]
        code = self._buttons.get(event.button)
        return [] if code is None else [(ecodes.EV_KEY, code, int(pressed))]

    def axis_range(self, code: int) -> tuple[int, int]:
        if code in (ecodes.ABS_HAT0X, ecodes.ABS_HAT0Y):
            return (-1, 1)
        return TRIGGER if code in (ecodes.ABS_Z, ecodes.ABS_RZ) else STICK

    def close(self) -> None:
        if self._handle is not None:
            self._handle.quit()
            self._handle = None


def open_sdl_gamepad() -> Gamepad:
    """The first game controller SDL knows; one line on why there is none."""
    pygame = _sdl()
    from pygame._sdl2 import controller

    for index in range(controller.get_count()):
        if controller.is_controller(index):
            pad = controller.Controller(index)
            joystick = pad.as_joystick()
            return Gamepad(SdlSource(joystick.get_instance_id(), joystick.get_name(), pad))
    joysticks = pygame.joystick.get_count()
    raise TeleopError(
        "SDL finds no game controller"
        + (f" ({joysticks} joystick(s) it has no layout for)" if joysticks else "")
        + "; plug one in, or use `gamepad` (evdev) with the kernel's names"
    )
