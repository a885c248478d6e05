"""A UR controller emulator on loopback: the real protocols, the plant's physics.

It serves what the real ``ur_rtde`` library and the driver talk to, on the ports a UR
controller uses: RTDE (30004), the script port the control script is uploaded through
(30003), the dashboard (29999), the Robotiq URCap socket (63352), plus the cell's
cameras as MJPEG over HTTP (8080) and a harness channel (30100) through which tests and
ground-truth evaluation do what a person at the cell does and read what only a
simulation knows. The arm is the plant (hidden effects and all), stepped in real time
at the controller's servo rate.

It is an emulator of the protocols, not URSim: no PolyScope, no URScript interpreter;
it runs what ur_rtde's control script asks through the registers (see
:mod:`.program`). Several emulators run side by side on different loopback addresses
(127.0.0.2, 127.0.0.3, ...), which is also how tests exercise the remote-control check
that ur_rtde skips on 127.0.0.1.
"""

from __future__ import annotations

import signal
import socket
import socketserver
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

from twinrl_robot.cell_file import CellFile
from twinrl_robot.errors import RobotError
from twinrl_robot.ur.emulator.arm import EmulatedArm
from twinrl_robot.ur.emulator.camera_server import CameraServer
from twinrl_robot.ur.emulator.program import ControlProgram
from twinrl_robot.ur.emulator.rtde_server import Registers, RTDEServer, received
from twinrl_robot.ur.emulator.script import complete_script
from twinrl_robot.ur.emulator.text_servers import Dashboard, Harness, LineServer, RobotiqSocket
from twinrl_robot.ur.gripper import STROKES
from twinrl_sim.tasks import Task

STOP_TIMEOUT = 5.0  # s for the emulator to close its ports when told to stop
CATCH_UP_LIMIT = 0.25  # s behind the wall clock past which the emulated arm skips ahead
SLIDER_PERCENTS = (0, 20, 100)  # the pendant's speed slider settings the harness can set


@dataclass(frozen=True)
class Ports:
    """The ports the emulator serves (a UR controller's own, and two of its own)."""

    rtde: int = 30004
    script: int = 30003
    dashboard: int = 29999
    gripper: int = 63352
    cameras: int = 8080
    harness: int = 30100


class Emulator:
    """The emulated controller of ``cell`` running ``task``'s plant.

    Args:
        cell: the cell file (servo rate, TCP offset, gripper, cameras).
        task: the task whose plant the arm stands in.
        effects: the plant's hidden effects (see :func:`twinrl_robot.plant.hidden_effects`).
        host: the loopback address to serve on.
    """

    def __init__(
        self,
        cell: CellFile,
        task: Task,
        *,
        effects: dict[str, Any] | None = None,
        host: str = "127.0.0.1",
        ports: Ports = Ports(),
    ) -> None:
        self.cell, self.host, self.ports = cell, host, ports
        self.arm = EmulatedArm(
            task,
            effects=effects,
            servo_hz=cell.arm.servo_rate,
            tcp_offset=cell.arm.tcp_offset,
            gripper_output=cell.gripper.output if cell.gripper.kind == "digital" else None,
        )
        self.registers = Registers()
        self.program = ControlProgram(self.arm, self.registers)
        self.remote_control = True
        self.overruns = 0  # servo periods the physics could not keep in real time
        self._servers: list[socketserver.BaseServer] = []
        self._running = False
        self._physics = threading.Thread(target=self._run_physics, name="physics", daemon=True)

    # ------------------------------------------------------------- lifecycle
    def start(self) -> Emulator:
        """Open every port (one clear error when one is taken) and start the physics."""
        ports, host = self.ports, self.host
        stroke = STROKES.get(self.cell.gripper.kind, 0.085)
        makers = [
            (
                "RTDE",
                ports.rtde,
                lambda a: RTDEServer(
                    a, self.arm.read, self.registers, self.arm.set_digital_outputs
                ),
            ),
            ("script", ports.script, lambda a: _ScriptServer(a, self.program)),
            (
                "dashboard",
                ports.dashboard,
                lambda a: LineServer(
                    a, Dashboard(self.arm, self._remote, self.program.end), _DASHBOARD_GREETING
                ),
            ),
            ("harness", ports.harness, lambda a: LineServer(a, Harness(self.arm, self._faults()))),
        ]
        if self.cell.gripper.kind.startswith("robotiq"):
            makers.append(
                (
                    "Robotiq",
                    self.cell.gripper.port,
                    lambda a: LineServer(a, RobotiqSocket(self.arm, stroke)),
                )
            )
        cameras = {c.name: (c.width, c.height, c.fps) for c in self.cell.cameras}
        known = set(self.arm.cell.layout.cameras)
        if cameras:
            unknown = sorted(set(cameras) - known)
            if unknown:
                raise RobotError(
                    f"the cell file's camera(s) {unknown} are not in the twin, which has "
                    f"{sorted(known)}; name the emulated cameras after the twin's"
                )
            makers.append(("cameras", ports.cameras, lambda a: CameraServer(a, self.arm, cameras)))
        for name, port, make in makers:
            try:
                server = make((host, port))
            except OSError as err:
                self.stop()
                raise RobotError(
                    f"cannot serve the emulated {name} port {host}:{port} ({err.strerror}); "
                    "another controller or emulator uses it: stop it or emulate on another "
                    "loopback address (127.0.0.2 and up)"
                ) from None
            self._servers.append(server)
            threading.Thread(target=server.serve_forever, name=name, daemon=True).start()
        self._running = True
        self._physics.start()
        return self

    def stop(self) -> None:
        self._running = False
        for server in self._servers:
            if isinstance(server, RTDEServer | CameraServer):
                server.running = False
            server.shutdown()
            server.server_close()
        self._servers.clear()
        if self._physics.is_alive():
            self._physics.join(timeout=2.0)

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---------------------------------------------------------------- physics
    def _run_physics(self) -> None:
        """Tick the arm each servo period. A real controller never loses a period: after
        a stall of this process the periods it missed run back to back, so the arm's time
        keeps to the wall clock rather than falling behind it; only a stall longer than
        :data:`CATCH_UP_LIMIT` is given up."""
        period = self.arm.period
        next_tick = time.monotonic()
        while self._running:
            self.program.cycle(next_tick)
            self.arm.tick()
            next_tick += period
            late = time.monotonic() - next_tick
            if late < 0:
                time.sleep(-late)
            elif late > period:
                self.overruns += 1
                if late > CATCH_UP_LIMIT:
                    next_tick = time.monotonic()

    # ----------------------------------------------------------------- faults
    def _remote(self) -> bool:
        return self.remote_control

    def _faults(self) -> dict[str, Any]:
        """What the harness may do to the cell, as a person or the world would."""

        def protective() -> None:
            self.arm.protective_stop("the harness triggered a protective stop")
            self.program.end("protective stop")

        def emergency() -> None:
            self.arm.emergency_stop()
            self.program.end("emergency stop")

        def local_mode() -> None:
            self.remote_control = False
            self.program.end("the controller left remote control")

        def remote_mode() -> None:
            self.remote_control = True

        def drop() -> None:
            for server in self._servers:
                if isinstance(server, RTDEServer):
                    server.drop_connections()

        return {
            "protective_stop": protective,
            "emergency_stop": emergency,
            "release_emergency_stop": self.arm.release_emergency_stop,
            "local_mode": local_mode,
            "remote_mode": remote_mode,
            "drop_connection": drop,
            **{
                f"speed_slider_{percent}": partial(self.arm.set_speed_fraction, percent / 100)
                for percent in SLIDER_PERCENTS
            },
        }


_DASHBOARD_GREETING = "Connected: Universal Robots Dashboard Server"


class _ScriptServer(socketserver.ThreadingTCPServer):
    """The script port: a complete ur_rtde control script (re)starts the program."""

    allow_reuse_address = True
    daemon_threads = True

    def __init__(self, address: tuple[str, int], program: ControlProgram) -> None:
        self.program = program
        super().__init__(address, _ScriptHandler)


class _ScriptHandler(socketserver.BaseRequestHandler):
    server: _ScriptServer

    def handle(self) -> None:
        text = ""
        for chunk in received(self.request):
            text += chunk.decode(errors="replace")
            script = complete_script(text)
            if script is not None:
                self.server.program.start(script)
                text = ""
            elif len(text) > 1_000_000:
                text = ""  # not a control script: the controller would reject it


def free_loopback_host(port: int = Ports.rtde, first: int = 2) -> str:
    """A loopback address (127.0.0.N, N >= ``first``) whose RTDE port is free."""
    for n in range(first, 255):
        host = f"127.0.0.{n}"
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((host, port))
            except OSError:
                continue
            return host
    raise RobotError("no free loopback address for an emulator (127.0.0.2-254 all busy)")


def banner(emulator: Emulator) -> str:
    """The line that says an emulator serves (``EmulatorProcess`` waits for it)."""
    cell, ports, host = emulator.cell, emulator.ports, emulator.host
    served = [f"RTDE {ports.rtde}", f"script {ports.script}", f"dashboard {ports.dashboard}"]
    if cell.gripper.kind.startswith("robotiq"):
        served.append(f"Robotiq {cell.gripper.port}")
    if cell.cameras:
        served.append(f"cameras http://{host}:{ports.cameras}/<name>")
    served.append(f"harness {ports.harness}")
    return (
        f"emulating {cell.arm.model} of cell {cell.name} at {host} "
        f"({cell.arm.servo_rate:g} Hz, task {emulator.arm.task.name}): {', '.join(served)}; "
        "an emulator of the controller's protocols backed by the plant, not URSim"
    )


def serve(emulator: Emulator, on_ready: Callable[[str], None]) -> None:
    """Run ``emulator`` until SIGINT or SIGTERM; ``on_ready`` gets :func:`banner` first."""
    stopped = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopped.set())
    emulator.start()
    on_ready(banner(emulator))
    stopped.wait()
    # Closing the ports must not keep the process alive (a client that never lets go).
    closing = threading.Thread(target=emulator.stop, daemon=True)
    closing.start()
    closing.join(STOP_TIMEOUT)
