"""A 3Dconnexion SpaceMouse over HID.

pyspacemouse knows every model's report layout (which bytes carry which axis, which
bits which button) and turns reports into axes in [-1, 1] in its right-handed Z-up
frame; hidapi's bundled library reads the reports (no system library needed). A
:class:`RecordedReports` port plays a recorded report stream back at its own pace:
how the driver is tested without the device, byte for byte what the device sent.

On Linux the person needs read access to the device's ``/dev/hidraw*`` node (a udev
rule; see the recording guide).
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from twinrl_robot.teleop.device import TeleopError, ThreadedDevice

READ_TIMEOUT_MS = 50  # one blocking read; the reader thread checks for close between reads
UNPLUGGED = (
    "the SpaceMouse stopped answering (unplugged, or its receiver lost it); the arm holds. "
    "Plug it back in and start the recording again: the session continues"
)


class HidPort:
    """One HID device by its path, as pyspacemouse's device reads it."""

    def __init__(self, path: bytes) -> None:
        import hid

        self.path = path
        self._device = hid.device()

    def open(self) -> None:
        self._device.open_path(self.path)

    def set_nonblocking(self, flag: bool) -> None:
        self._device.set_nonblocking(int(flag))

    def read(self, size: int) -> bytes:
        return bytes(self._device.read(max(size, 64), READ_TIMEOUT_MS))

    @property
    def product_string(self) -> str:
        return self._device.get_product_string() or ""

    @property
    def manufacturer_string(self) -> str:
        return self._device.get_manufacturer_string() or ""

    @property
    def serial_number(self) -> str:
        return self._device.get_serial_number_string() or ""

    release_number = ""

    def close(self) -> None:
        self._device.close()


class RecordedReports:
    """A recorded report stream (``[(seconds since the first, report bytes)]``) played
    back in real time from :meth:`open`; after the last report it is silent, or gone
    (``unplug_at_end``: reads fail as an unplugged device's do)."""

    def __init__(
        self, reports: Sequence[tuple[float, bytes]], *, unplug_at_end: bool = False
    ) -> None:
        self.reports = list(reports)
        self.unplug_at_end = unplug_at_end
        self.product_string = self.manufacturer_string = self.serial_number = "recorded"
        self.release_number = ""
        self._start: float | None = None
        self._next = 0

    @classmethod
    def load(cls, path: str | Path, *, unplug_at_end: bool = False) -> tuple[str, RecordedReports]:
        """A recording file: a JSON header line ``{"device": <pyspacemouse model>}``, then
        one ``{"t": s, "report": hex}`` line per report. Returns the model and the port."""
        lines = Path(path).read_text().splitlines()
        try:
            device = json.loads(lines[0])["device"]
            reports = [
                (float(r["t"]), bytes.fromhex(r["report"])) for r in map(json.loads, lines[1:])
            ]
        except (IndexError, KeyError, ValueError) as err:
            raise TeleopError(f"{path} is not a SpaceMouse report recording ({err})") from None
        return device, cls(reports, unplug_at_end=unplug_at_end)

    def open(self) -> None:
        self._start = time.monotonic()

    def set_nonblocking(self, flag: bool) -> None:
        """Reads wait for the next report's time (up to the read timeout) either way."""

    def read(self, size: int) -> bytes:
        assert self._start is not None, "open the port first"
        if self._next >= len(self.reports):
            if self.unplug_at_end:
                raise OSError("read error")
            time.sleep(READ_TIMEOUT_MS / 1000)
            return b""
        t, report = self.reports[self._next]
        wait = self._start + t - time.monotonic()
        if wait > READ_TIMEOUT_MS / 1000:
            time.sleep(READ_TIMEOUT_MS / 1000)
            return b""
        time.sleep(max(0.0, wait))
        self._next += 1
        return report

    def close(self) -> None:
        self._next = len(self.reports)


class SpaceMouse(ThreadedDevice):
    """A SpaceMouse as an :class:`~twinrl_robot.teleop.device.InputDevice`: axes ``x y z
    roll pitch yaw`` (pyspacemouse's Z-up frame), buttons by pyspacemouse's names
    (``LEFT``, ``RIGHT``, ``BTN_1`` ...)."""

    kind = "spacemouse"
    continuous = True  # it streams reports while the cap is deflected

    def __init__(self, port: Any, model: str) -> None:
        from pyspacemouse.config_helpers import apply_axis_convention
        from pyspacemouse.device import SpaceMouseDevice
        from pyspacemouse.loader import get_device_specs
        from pyspacemouse.types import AxisConvention

        specs = get_device_specs()
        if model not in specs:
            raise TeleopError(f"unknown SpaceMouse model '{model}'; known: {', '.join(specs)}")
        info = apply_axis_convention(specs[model], AxisConvention.HID_Z_UP)
        self.model = model
        self._mouse = SpaceMouseDevice(info=info, device=port)
        try:
            self._mouse.open()
        except (OSError, RuntimeError) as err:
            raise TeleopError(
                f"cannot open the {model} ({err}); on Linux give your user read access to "
                "its /dev/hidraw* node (a udev rule, see the recording guide)"
            ) from None
        self._held: frozenset[str] = frozenset()
        self._last_report = -1.0
        self._start("spacemouse", UNPLUGGED)

    def _poll(self) -> None:
        state = self._mouse.read()
        if state.t == self._last_report:
            return
        self._last_report = state.t
        buttons = frozenset(
            self._mouse.get_button_name(i) for i, down in enumerate(state.buttons) if down
        )
        axes = {name: getattr(state, name) for name in ("x", "y", "z", "roll", "pitch", "yaw")}
        self._state.update(axes, pressed=buttons - self._held, released=self._held - buttons)
        self._held = buttons

    def _release(self) -> None:
        self._mouse.close()


def open_spacemouse() -> SpaceMouse:
    """The first SpaceMouse plugged in, or one line on why there is none."""
    import hid
    from pyspacemouse.loader import get_device_specs

    known = {(s.vendor_id, s.product_id): name for name, s in get_device_specs().items()}
    for device in hid.enumerate():
        model = known.get((device["vendor_id"], device["product_id"]))
        if model is not None:
            return SpaceMouse(HidPort(device["path"]), model)
    raise TeleopError(
        "no SpaceMouse is plugged in (no HID device with a 3Dconnexion model's ids); plug it "
        "in, or choose another `teleop` (gamepad, keyboard)"
    )
