"""The emulator's line-based servers: the dashboard (29999), the Robotiq URCap socket
(63352), and the harness channel that stands in for the person at the cell.

Each answers one line per request line, as the real servers do; each connection is
served by its own thread.
"""

from __future__ import annotations

import json
import socketserver
from collections.abc import Callable

from twinrl_robot.ur.emulator.arm import EmulatedArm, RobotMode, SafetyMode
from twinrl_sim.tasks import TaskConfig

POLYSCOPE_VERSION = "5.15.0.1234"
SERIAL_NUMBER = "20260000000"
DASHBOARD_GREETING = "Connected: Universal Robots Dashboard Server"


class LineServer(socketserver.ThreadingTCPServer):
    """A threading TCP server that answers each line with ``answer(line)``."""

    allow_reuse_address = True
    daemon_threads = True

    def __init__(
        self,
        address: tuple[str, int],
        answer: Callable[[str], str | None],
        greeting: str | None = None,
    ) -> None:
        self.answer, self.greeting = answer, greeting
        super().__init__(address, _LineHandler)


class _LineHandler(socketserver.StreamRequestHandler):
    server: LineServer

    def handle(self) -> None:
        if self.server.greeting:
            self.wfile.write(self.server.greeting.encode() + b"\n")
        for raw in self.rfile:
            line = raw.decode(errors="replace").strip()
            if not line:
                continue
            reply = self.server.answer(line)
            if reply is None:  # e.g. "quit": close the connection
                return
            self.wfile.write(reply.encode() + b"\n")


class Dashboard:
    """The dashboard server's answers for the arm (robot and safety modes, stops).

    ``end_program(reason)`` stops the control program as its ``stop`` command does."""

    def __init__(
        self,
        arm: EmulatedArm,
        remote_control: Callable[[], bool],
        end_program: Callable[[str], None],
    ) -> None:
        self.arm, self.remote_control, self.end_program = arm, remote_control, end_program

    def __call__(self, line: str) -> str | None:
        command = line.strip().lower()
        arm = self.arm
        if command == "quit":
            return None
        if command == "robotmode":
            return f"Robotmode: {RobotMode(arm.robot_mode).name}"
        if command in ("safetymode", "safetystatus"):
            label = "Safetystatus" if command == "safetystatus" else "Safetymode"
            return f"{label}: {SafetyMode(arm.safety_mode).name}"
        if command == "programstate":
            state = "PLAYING" if arm.program_running else "STOPPED"
            return f"{state} rtde_control"
        if command == "running":
            return f"Program running: {str(arm.program_running).lower()}"
        if command == "is in remote control":
            return str(self.remote_control()).lower()
        if command == "polyscopeversion":
            return f"URSoftware {POLYSCOPE_VERSION} (Nov 2026)"
        if command == "version":
            return POLYSCOPE_VERSION
        if command == "get serial number":
            return SERIAL_NUMBER
        if command == "get robot model":
            return "UR5"
        if command == "unlock protective stop":
            if arm.unlock_protective_stop():
                return "Protective stop releasing"
            return (
                "Cannot unlock protective stop until 5s after occurrence. Always inspect cause "
                "of protective stop before unlocking"
            )
        if command == "close safety popup":
            return "closing safety popup"
        if command == "close popup":
            return "closing popup"
        if command == "power on":
            arm.release_emergency_stop()
            return "Powering on"
        if command == "brake release":
            return "Brake releasing"
        if command == "power off":
            arm.emergency_stop()
            return "Powering off"
        if command == "stop":
            self.end_program("the dashboard stopped the program")
            return "Stopped"
        if command == "pause":
            arm.stop()
            return "Pausing program"
        if command == "play":
            return "Failed to execute: play"  # no installed program to play here
        return f"could not understand: '{line}'"


class RobotiqSocket:
    """The Robotiq URCap's socket for the arm's gripper (``POS`` 0 open .. 255 closed)."""

    def __init__(self, arm: EmulatedArm, stroke: float) -> None:
        self.arm, self.stroke = arm, stroke
        self.values = {"ACT": 0, "GTO": 0, "SPE": 255, "FOR": 150, "POS": 0, "STA": 0}

    def __call__(self, line: str) -> str | None:
        words = line.split()
        if len(words) >= 2 and words[0] == "GET":
            name = words[1]
            if name == "POS":
                closed = 1.0 - self.arm.read().gripper_opening / self.stroke
                return f"POS {round(255 * min(max(closed, 0.0), 1.0))}"
            if name == "PRE":
                return f"PRE {round(255 * self.arm.gripper_position)}"
            if name == "OBJ":
                return "OBJ 3"
            if name == "FLT":
                return "FLT 0"
            return f"{name} {self.values.get(name, 0)}"
        if len(words) >= 3 and words[0] == "SET" and len(words) % 2 == 1:
            for name, value in zip(words[1::2], words[2::2], strict=True):
                if not value.lstrip("-").isdigit():
                    return "?"
                self.values[name] = int(value)
            self.values["STA"] = 3 if self.values["ACT"] else 0
            if self.values["ACT"] and self.values["GTO"]:
                self.arm.gripper_position = min(max(self.values["POS"], 0), 255) / 255.0
            return "ack"
        return "?"


class Harness:
    """The harness channel: what a person does at the cell (set up a configuration,
    press the emergency stop, take the robot out of remote control) and what only a
    simulation knows (the task's success, the objects' poses). One JSON object per line.
    The driver never uses it; tests and ``--ground-truth`` evaluation do."""

    def __init__(self, arm: EmulatedArm, faults: dict[str, Callable[[], None]]) -> None:
        self.arm, self.faults = arm, faults

    def __call__(self, line: str) -> str | None:
        try:
            request = json.loads(line)
            kind = request["do"]
            if kind == "arrange":
                self.arm.arrange(TaskConfig.from_dict(request["config"]))
                return json.dumps({"ok": True})
            if kind == "truth":
                return json.dumps({"ok": True, **self.arm.ground_truth()})
            if kind == "reading":
                reading = self.arm.read()
                return json.dumps(
                    {
                        "ok": True,
                        "q": reading.q.tolist(),
                        "qd": reading.qd.tolist(),
                        "timestamp": reading.timestamp,
                        "program_running": reading.runtime_state == 2,
                        "gripper_opening": reading.gripper_opening,
                        "safety_mode": reading.safety_mode,
                    }
                )
            if kind in self.faults:
                self.faults[kind]()
                return json.dumps({"ok": True})
            return json.dumps({"ok": False, "error": f"unknown request {kind!r}"})
        except (ValueError, KeyError, TypeError) as err:
            return json.dumps({"ok": False, "error": str(err)})
