"""twinrl's teleop devices as LeRobot :class:`~lerobot.teleoperators.teleoperator.Teleoperator`\\ s.

Each reads its device through twinrl's own :class:`~twinrl_robot.teleop.teleop.Teleop`
with the map of a cell file's ``teleop`` section (or the defaults) and gives the
end-effector action :class:`~twinrl_robot.lerobot_plugin.robot.TwinrlUR` takes: ``dx dy
dz rx ry rz`` scaled from the device's deflection and ``gripper``, toggled by the map's
``gripper`` button. The deadman holds: no deflection, a released deadman button, or a
device that went silent or away gives zero motion, so the arm holds where it is. The
map's other buttons (success, discard, takeover, ...) have no place in lerobot's loop
and are ignored; lerobot's keyboard keys end and redo episodes.
"""

from __future__ import annotations

import json
import logging
from abc import abstractmethod
from pathlib import Path
from typing import Any

from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected

from twinrl_data.lerobot_io import ACTION_NAMES
from twinrl_robot.lerobot_plugin.config import (
    TwinrlGamepadConfig,
    TwinrlSpaceMouseConfig,
    TwinrlTeleopConfig,
)
from twinrl_robot.teleop.device import InputDevice, TeleopError
from twinrl_robot.teleop.gamepad import RecordedEvents
from twinrl_robot.teleop.teleop import Teleop

logger = logging.getLogger(__name__)


class TwinrlTeleoperator(Teleoperator):
    """A twinrl teleop device behind lerobot's teleoperator API; subclasses open it."""

    config_class: type[TwinrlTeleopConfig]

    def __init__(self, config: TwinrlTeleopConfig) -> None:
        super().__init__(config)
        self.config = config
        self.map = config.device_map()
        self._teleop: Teleop | None = None
        self._lost_said = False

    @property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(ACTION_NAMES, float)

    @property
    def feedback_features(self) -> dict[str, type]:
        return {}  # none of these devices can push back

    @property
    def is_connected(self) -> bool:
        return self._teleop is not None

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        """Open the device (or its recording); it needs no calibration."""
        self._teleop = Teleop(self._open_device(), self.map)
        logger.info("%s connected", self)

    @abstractmethod
    def _open_device(self) -> InputDevice: ...

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate: the map's deadband absorbs a cap's or stick's rest."""

    def configure(self) -> None:
        """Nothing to configure: the map comes from the cell file."""

    @check_if_not_connected
    def get_action(self) -> dict[str, float]:
        """The person's action now (zero motion when they hold, or the device is gone)."""
        assert self._teleop is not None
        step = self._teleop.step()
        if self._teleop.lost and not self._lost_said:
            logger.warning(self._teleop.lost)
            self._lost_said = True
        return dict(zip(ACTION_NAMES, map(float, step.action), strict=True))

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        """Ignored: the devices have no force feedback."""

    @check_if_not_connected
    def disconnect(self) -> None:
        assert self._teleop is not None
        teleop, self._teleop = self._teleop, None
        teleop.close()


class TwinrlSpaceMouse(TwinrlTeleoperator):
    """A 3Dconnexion SpaceMouse (see :mod:`twinrl_robot.teleop.spacemouse`)."""

    config_class = TwinrlSpaceMouseConfig
    name = "twinrl_spacemouse"

    def _open_device(self) -> InputDevice:
        from twinrl_robot.teleop.spacemouse import RecordedReports, SpaceMouse, open_spacemouse

        if self.config.recorded is None:
            return open_spacemouse()
        model, port = RecordedReports.load(self.config.recorded)
        return SpaceMouse(port, model)


class TwinrlGamepad(TwinrlTeleoperator):
    """A gamepad through evdev or SDL (see :mod:`twinrl_robot.teleop.gamepad`)."""

    config_class = TwinrlGamepadConfig
    name = "twinrl_gamepad"
    config: TwinrlGamepadConfig

    def _open_device(self) -> InputDevice:
        from twinrl_robot.teleop.gamepad import Gamepad, open_gamepad

        if self.config.recorded is not None:
            return Gamepad(load_gamepad_events(self.config.recorded))
        if self.config.device == "sdl":
            from twinrl_robot.teleop.gamepad_sdl import open_sdl_gamepad

            return open_sdl_gamepad()
        return open_gamepad(self.config.device or None)


def load_gamepad_events(path: str | Path) -> RecordedEvents:
    """An evdev event recording, played back from now: a JSON header line with each
    axis's range, ``{"ranges": {"ABS_X": [-32768, 32767], ...}}``, then one event a line,
    ``{"t": seconds, "type": "EV_KEY", "code": "BTN_TL", "value": 1}`` (evdev's names)."""
    from evdev import ecodes

    lines = Path(path).read_text().splitlines()
    try:
        ranges = {
            ecodes.ecodes[name]: (int(low), int(high))
            for name, (low, high) in json.loads(lines[0])["ranges"].items()
        }
        events = [
            (float(e["t"]), ecodes.ecodes[e["type"]], ecodes.ecodes[e["code"]], int(e["value"]))
            for e in map(json.loads, lines[1:])
        ]
    except (IndexError, KeyError, TypeError, ValueError) as err:
        raise TeleopError(f"{path} is not a gamepad event recording ({err!r})") from None
    return RecordedEvents(events, ranges)
