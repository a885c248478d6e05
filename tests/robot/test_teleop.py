"""Teleop devices without hardware: the SpaceMouse through recorded HID report bytes,
the gamepad through recorded evdev events (and a virtual uinput pad where the kernel
offers one) and through SDL events posted into pygame's queue, the keyboard through a
pseudo-terminal; their maps, deadman and marks."""

from __future__ import annotations

import os
import pty
import struct
import time

import numpy as np
import pytest

from twinrl_robot.cell_file import CellFileError, parse_cell
from twinrl_robot.recording import Marks
from twinrl_robot.teleop import TeleopError, open_teleop
from twinrl_robot.teleop.device import DeviceState
from twinrl_robot.teleop.gamepad import Gamepad, RecordedEvents
from twinrl_robot.teleop.settings import DEFAULT_MAPS, TeleopSpec
from twinrl_robot.teleop.spacemouse import RecordedReports, SpaceMouse
from twinrl_robot.teleop.teleop import STALE, Teleop, TeleopOperator
from twinrl_robot.teleop.terminal import FIRST_HOLD, Keyboard, TerminalKeys, decode


def _motion_report(x=0, y=0, z=0, rx=0, ry=0, rz=0) -> bytes:
    """A SpaceMouse Wireless motion report: id 1, six little-endian int16 counts."""
    return bytes([1]) + struct.pack("<6h", x, y, z, rx, ry, rz)


def _button_report(left=False, right=False) -> bytes:
    return bytes([3, int(left) | int(right) << 1])


def _settle(teleop: Teleop, seconds: float):
    time.sleep(seconds)
    return teleop.step()


def test_spacemouse_reports_become_actions_with_deadband_gripper_and_unplug() -> None:
    # Push the cap 100 % along the device's x, 5 % along y (inside the deadband), then
    # press and release the left button, let go, and the receiver drops out.
    reports = [
        (0.00, _motion_report(x=350, y=-17)),
        (0.30, _button_report(left=True)),
        (0.35, _button_report()),
        (0.60, _motion_report()),
    ]
    port = RecordedReports(reports, unplug_at_end=True)
    teleop = Teleop(SpaceMouse(port, "SpaceMouseWireless"), DEFAULT_MAPS["spacemouse"])
    step = _settle(teleop, 0.15)
    translation = DEFAULT_MAPS["spacemouse"].translation
    np.testing.assert_allclose(step.action[:3], [translation, 0, 0], atol=1e-6)
    assert step.moving and teleop.gripper == 0.0
    step = _settle(teleop, 0.3)  # pressed and released since: the tap still counts
    assert "gripper" in step.events and teleop.gripper == 1.0
    step = _settle(teleop, 0.3)
    assert not step.moving and step.action[6] == 1.0
    step = _settle(teleop, 0.3)
    assert teleop.lost is not None and "unplugged" in teleop.lost
    assert not step.moving and step.action[6] == 1.0  # the arm holds, the gripper stays
    teleop.close()


def test_a_silent_spacemouse_holds_the_arm() -> None:
    # Lift the cap (HID's z points down), then silence.
    port = RecordedReports([(0.0, _motion_report(z=-350))])
    teleop = Teleop(SpaceMouse(port, "SpaceMouseWireless"), DEFAULT_MAPS["spacemouse"])
    assert _settle(teleop, 0.05).action[2] > 0
    assert not _settle(teleop, STALE + 0.1).moving
    teleop.close()


def test_the_recorded_report_file_and_unknown_models_are_checked(tmp_path) -> None:
    path = tmp_path / "reports.jsonl"
    path.write_text('{"device": "SpaceMouseWireless"}\n{"t": 0.0, "report": "01"}\n')
    model, port = RecordedReports.load(path)
    assert model == "SpaceMouseWireless" and port.reports == [(0.0, b"\x01")]
    path.write_text("not json\n")
    with pytest.raises(TeleopError, match="not a SpaceMouse report recording"):
        RecordedReports.load(path)
    with pytest.raises(TeleopError, match="unknown SpaceMouse model"):
        SpaceMouse(RecordedReports([]), "SpaceBall9000")


def test_no_spacemouse_plugged_in_is_one_line() -> None:
    with pytest.raises(TeleopError, match="no SpaceMouse is plugged in"):
        open_teleop("spacemouse")


STICK = (-32768, 32767)


def _pad(events, **kwargs) -> Teleop:
    from evdev import ecodes

    ranges = {
        ecodes.ABS_X: STICK,
        ecodes.ABS_Y: STICK,
        ecodes.ABS_RX: STICK,
        ecodes.ABS_Z: (0, 255),
    }
    return Teleop(Gamepad(RecordedEvents(events, ranges, **kwargs)), DEFAULT_MAPS["gamepad"])


def test_gamepad_moves_only_while_the_deadman_is_held() -> None:
    from evdev import ecodes

    KEY, ABS = ecodes.EV_KEY, ecodes.EV_ABS
    teleop = _pad(
        [
            (0.00, ABS, ecodes.ABS_Y, -32768),  # left stick fully up: +x, but no deadman
            (0.30, KEY, ecodes.BTN_TL, 1),  # deadman held
            (0.60, KEY, ecodes.BTN_A, 1),  # BTN_A is BTN_SOUTH: the gripper
            (0.65, KEY, ecodes.BTN_A, 0),
            (0.90, KEY, ecodes.BTN_TL, 0),  # deadman released
            (1.20, KEY, ecodes.BTN_NORTH, 1),  # success
            (1.50, ecodes.EV_SYN, 0, 0),  # then the pad drops out
        ],
        unplug_at_end=True,
    )
    assert not _settle(teleop, 0.15).moving
    step = _settle(teleop, 0.3)
    np.testing.assert_allclose(step.action[0], DEFAULT_MAPS["gamepad"].translation, rtol=1e-3)
    step = _settle(teleop, 0.3)
    assert step.events == ("gripper",) and step.action[6] == 1.0
    assert not _settle(teleop, 0.3).moving
    assert _settle(teleop, 0.3).events == ("success",)
    _settle(teleop, 0.4)
    assert teleop.lost is not None and "gamepad went away" in teleop.lost
    teleop.close()


def test_gamepad_scales_sticks_about_their_centre_and_triggers_from_zero() -> None:
    from evdev import ecodes

    pad = Gamepad(RecordedEvents([], {ecodes.ABS_X: (0, 255), ecodes.ABS_Z: (0, 1023)}))
    assert pad._scaled("ABS_X", ecodes.ABS_X, 128) == pytest.approx(0.0, abs=0.01)
    assert pad._scaled("ABS_Z", ecodes.ABS_Z, 1023) == pytest.approx(1.0)
    assert pad._scaled("ABS_Z", ecodes.ABS_Z, 0) == pytest.approx(0.0)
    pad.close()


@pytest.mark.skipif(
    not os.access("/dev/uinput", os.W_OK), reason="no writable /dev/uinput on this kernel"
)
def test_a_virtual_uinput_gamepad_drives_the_evdev_reader() -> None:
    from evdev import AbsInfo, UInput, ecodes

    capabilities = {
        ecodes.EV_KEY: [ecodes.BTN_SOUTH, ecodes.BTN_TL],
        ecodes.EV_ABS: [
            (ecodes.ABS_X, AbsInfo(0, *STICK, 16, 128, 0)),
            (ecodes.ABS_Y, AbsInfo(0, *STICK, 16, 128, 0)),
        ],
    }
    with UInput(capabilities, name="twinrl test pad") as pad:
        time.sleep(0.3)  # udev makes the node
        teleop = open_teleop(f"gamepad:{pad.device.path}")
        pad.write(ecodes.EV_KEY, ecodes.BTN_TL, 1)
        pad.write(ecodes.EV_ABS, ecodes.ABS_Y, -32768)
        pad.syn()
        assert _settle(teleop, 0.2).action[0] > 0
        teleop.close()


def _sdl_events(*events: tuple[float, str, dict]) -> None:
    """Post SDL controller events into pygame's own queue, each at its time (s)."""
    import pygame

    start = time.monotonic()
    for at, kind, fields in events:
        time.sleep(max(0.0, start + at - time.monotonic()))
        pygame.event.post(pygame.event.Event(getattr(pygame, kind), **fields))


def test_an_sdl_gamepad_maps_by_position_onto_the_gamepad_map() -> None:
    import threading

    from twinrl_robot.teleop.gamepad_sdl import SdlSource

    pad = SdlSource(instance_id=7, name="test pad")  # brings pygame up, quietly
    teleop = Teleop(Gamepad(pad), DEFAULT_MAPS["gamepad"])
    import pygame

    def button(name: str) -> dict:
        return {"instance_id": 7, "button": getattr(pygame, f"CONTROLLER_BUTTON_{name}")}

    def axis(name: str, value: int) -> dict:
        code = getattr(pygame, f"CONTROLLER_AXIS_{name}")
        return {"instance_id": 7, "axis": code, "value": value}

    poster = threading.Thread(
        target=_sdl_events,
        args=(
            (0.00, "CONTROLLERAXISMOTION", axis("LEFTY", -32768)),  # left stick up: +x
            (0.00, "CONTROLLERBUTTONDOWN", button("LEFTSHOULDER")),  # the deadman
            # Another pad's stick is not this one's.
            (0.00, "CONTROLLERAXISMOTION", {**axis("LEFTX", 32767), "instance_id": 8}),
            (0.30, "CONTROLLERBUTTONDOWN", button("DPAD_LEFT")),  # the hat: tilt about y
            (0.60, "CONTROLLERBUTTONUP", button("DPAD_LEFT")),
            (0.60, "CONTROLLERBUTTONDOWN", button("A")),  # bottom face button: gripper
            (0.65, "CONTROLLERBUTTONUP", button("A")),
            (0.90, "CONTROLLERBUTTONUP", button("LEFTSHOULDER")),
            (0.90, "CONTROLLERBUTTONDOWN", button("Y")),  # top face button: success
            (1.20, "CONTROLLERDEVICEREMOVED", {"instance_id": 7}),
        ),
    )
    poster.start()
    step = _settle(teleop, 0.15)
    translation = DEFAULT_MAPS["gamepad"].translation
    np.testing.assert_allclose(step.action[:3], [translation, 0, 0], rtol=1e-3, atol=1e-9)
    step = _settle(teleop, 0.3)
    assert abs(step.action[3]) > 0 and step.action[0] > 0  # the D-pad tilts as well
    step = _settle(teleop, 0.3)
    assert step.events == ("gripper",) and step.action[6] == 1.0 and step.action[3] == 0
    step = _settle(teleop, 0.3)
    assert step.events == ("success",) and not step.moving
    poster.join()
    _settle(teleop, 0.2)
    assert teleop.lost is not None and "gamepad went away" in teleop.lost
    teleop.close()


def test_no_sdl_game_controller_is_one_line() -> None:
    with pytest.raises(TeleopError, match="SDL finds no game controller") as refused:
        open_teleop("gamepad:sdl")
    assert "\n" not in str(refused.value)


@pytest.fixture
def terminal():
    leader, follower = pty.openpty()
    keys = TerminalKeys(follower)
    yield leader, keys
    keys.close()
    os.close(leader)
    os.close(follower)


def test_terminal_bytes_decode_to_keys() -> None:
    assert decode(b"i\x1b[D \r\x1b[5~q\x1b[1;5C") == [
        "i",
        "left",
        "space",
        "enter",
        "pageup",
        "q",
        "?",
    ]


def test_keyboard_keys_hold_while_repeating_and_stop_when_released(terminal) -> None:
    leader, keys = terminal
    teleop = Teleop(Keyboard(keys), DEFAULT_MAPS["keyboard"])
    os.write(leader, b"i")
    step = _settle(teleop, 0.1)
    assert step.action[0] == pytest.approx(DEFAULT_MAPS["keyboard"].translation)
    for _ in range(5):  # the terminal repeats a held key
        os.write(leader, b"i")
        time.sleep(0.05)
    assert teleop.step().moving
    assert not _settle(teleop, FIRST_HOLD + 0.1).moving  # released
    os.write(leader, b"\x1b[D ")  # left arrow turns; space toggles the gripper
    step = _settle(teleop, 0.1)
    assert step.action[5] > 0 and step.events == ("gripper",)


def test_marks_and_a_typed_note_come_from_the_terminal(terminal) -> None:
    leader, keys = terminal
    marks = Marks(keys)
    os.write(leader, b"nslow grip\x7f\x7fip\rs")
    time.sleep(0.2)
    assert marks.take() == "success"
    assert marks.note == "slow grip" and not keys.typing


def test_the_keyboard_needs_a_terminal() -> None:
    with pytest.raises(TeleopError, match="terminal"):
        open_teleop("keyboard")
    read, write = os.pipe()
    with pytest.raises(TeleopError, match="not one"):
        TerminalKeys(read)
    os.close(read)
    os.close(write)


class _Buttons:
    """A device whose buttons the test presses."""

    kind, continuous = "test", False

    def __init__(self) -> None:
        self.state = DeviceState()

    def read(self, observation=None) -> DeviceState:
        return self.state

    def episode(self, task, config) -> None: ...

    def close(self) -> None: ...


def test_the_operator_takes_over_and_hands_back_with_one_button() -> None:
    device = _Buttons()
    operator = TeleopOperator(Teleop(device, DEFAULT_MAPS["spacemouse"]))
    operator.reset(None, None)
    observation = {"observation.state": np.array([0.08], np.float32)}
    assert operator.intervene(observation, None) is None
    device.state = DeviceState({"x": 1.0}, frozenset({"RIGHT"}), time.monotonic())
    observation = {"observation.state": np.array([0.03], np.float32)}  # holding something
    action = operator.intervene(observation, None)
    assert action is not None and action[0] > 0 and action[6] == 1.0  # closed, as it was
    assert operator.takeovers == 1
    device.state = DeviceState({}, frozenset(), time.monotonic())
    assert operator.intervene(observation, None) is not None  # still in control
    device.state = DeviceState({}, frozenset({"RIGHT"}), time.monotonic())
    assert operator.intervene(observation, None) is None  # handed back


def _cell(teleop: dict) -> dict:
    return {"name": "c", "twin": "pick_place", "arm": {"host": "127.0.0.1"}, "teleop": teleop}


def test_cell_file_teleop_maps_override_defaults_and_refuse_unknown_names() -> None:
    cell = parse_cell(_cell({"spacemouse": {"axes": ["y", "-x", "z", "pitch", "-roll", "yaw"]}}))
    device_map = cell.teleop.device_map("spacemouse")
    assert device_map.axes[1] == "-x" and device_map.buttons == DEFAULT_MAPS["spacemouse"].buttons
    with pytest.raises(CellFileError, match=r"unknown event\(s\) \['jump'\]"):
        parse_cell(_cell({"gamepad": {"buttons": {"jump": "BTN_A"}}}))
    with pytest.raises(CellFileError, match="unknown device axis 'rx'"):
        parse_cell(_cell({"spacemouse": {"axes": ["x", "y", "z", "rx", "ry", "rz"]}}))
    with pytest.raises(TeleopError, match="unknown teleop device 'joystick'"):
        open_teleop("joystick", TeleopSpec())
