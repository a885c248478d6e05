"""The emulator's RTDE server (port 30004): UR's Real-Time Data Exchange protocol v2.

Every package is ``uint16 size | uint8 type | payload``, big-endian, the size counting
the 3-byte header. A client negotiates the protocol version ('V'), asks the controller
version ('v'), sets up an output recipe ('O': frequency and variable names, answered
with a recipe id and the variables' types) and input recipes ('I': answered with a
recipe id and types, ``IN_USE`` where another client writes that variable), starts
('S'), then receives data packages ('U') at its frequency and sends its own ('U' with
an input recipe id). Text messages ('M') carry the controller's warnings.

The server keeps the controller's registers (:class:`Registers`) and publishes the arm's
readings (:class:`~twinrl_robot.ur.emulator.arm.ArmReading`) under RTDE's names.
"""

from __future__ import annotations

import contextlib
import socket
import socketserver
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping

import numpy as np

from twinrl_robot.ur.emulator.arm import ArmReading, SafetyMode

PROTOCOL_VERSION = 2
CONTROLLER_VERSION = (5, 15, 0, 1234)  # PolyScope 5.15 (e-Series)
CLOCK_TOLERANCE = 1e-6  # s: two readings this close in time are one control cycle
POLL = 5e-4  # s between looks for the next control cycle while streaming
REQUEST_PROTOCOL_VERSION, GET_URCONTROL_VERSION = ord("V"), ord("v")
TEXT_MESSAGE, DATA_PACKAGE = ord("M"), ord("U")
SETUP_OUTPUTS, SETUP_INPUTS, START, PAUSE = ord("O"), ord("I"), ord("S"), ord("P")


def _names(text: str) -> list[str]:
    """Variable names written as one space-separated string (RTDE's lists are long)."""
    return text.split()


FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_VECTOR6D = _names(
    "target_q target_qd target_qdd target_current target_moment actual_q actual_qd "
    "actual_qdd actual_current actual_current_as_torque actual_moment joint_control_output "
    "actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed "
    "joint_temperatures actual_joint_voltage ft_raw_wrench payload_inertia "
    "actual_current_window external_force_torque"
)
_DOUBLE = _names(
    "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum "
    "actual_main_voltage actual_robot_voltage actual_robot_current standard_analog_input0 "
    "standard_analog_input1 standard_analog_output0 standard_analog_output1 io_current "
    "tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature "
    "tcp_force_scalar payload speed_slider_fraction standard_analog_output_0 "
    "standard_analog_output_1 joint_position_deviation_ratio collision_detection_ratio"
)
_UINT32 = _names(
    "runtime_state robot_status_bits safety_status_bits analog_io_types tool_mode "
    "tool_analog_input_types output_bit_registers0_to_31 output_bit_registers32_to_63 "
    "input_bit_registers0_to_31 input_bit_registers32_to_63 speed_slider_mask "
    "script_control_line euromap67_input_bits euromap67_output_bits"
)
_UINT8 = _names(
    "standard_digital_output_mask standard_digital_output configurable_digital_output_mask "
    "configurable_digital_output tool_digital_output_mask tool_digital_output "
    "standard_analog_output_mask standard_analog_output_type tool_output_mode "
    "tool_digital_output0_mode tool_digital_output1_mode"
)
VARIABLE_TYPES: dict[str, str] = {
    **{name: "VECTOR6D" for name in _VECTOR6D},
    **{name: "DOUBLE" for name in _DOUBLE},
    **{name: "UINT32" for name in _UINT32},
    **{name: "UINT8" for name in _UINT8},
    "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "tool_output_voltage": "INT32",
    "joint_mode": "VECTOR6INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "payload_cog": "VECTOR3D",
    **{f"{d}_int_register_{i}": "INT32" for d in ("input", "output") for i in range(48)},
    **{f"{d}_double_register_{i}": "DOUBLE" for d in ("input", "output") for i in range(48)},
    **{f"{d}_bit_register_{i}": "BOOL" for d in ("input", "output") for i in range(64, 128)},
}


def pack(kind: int, payload: bytes = b"") -> bytes:
    return struct.pack(">HB", len(payload) + 3, kind) + payload


class Registers:
    """The controller's general-purpose registers and which client writes which input."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.values: dict[str, float | int | bool] = {}
        self.writers: dict[str, int] = {}  # input variable -> client id that set it up
        self.updated: dict[str, float] = {}  # input variable -> when a client last wrote it
        # Told of every input package (its values, when it came), under the lock: the
        # control program keeps each command with the arguments it came with.
        self.listener: Callable[[Mapping[str, float | int | bool], float], None] | None = None

    def get(self, name: str, default: float | int = 0) -> float | int | bool:
        with self.lock:
            return self.values.get(name, default)

    def set(self, name: str, value: float | int | bool) -> None:
        with self.lock:
            self.values[name] = value

    def release(self, client: int) -> None:
        with self.lock:
            for name in [n for n, c in self.writers.items() if c == client]:
                del self.writers[name]


def received(connection: socket.socket) -> Iterator[bytes]:
    """What a client sends, chunk by chunk, until it closes or the connection fails."""
    while True:
        try:
            chunk = connection.recv(65536)
        except OSError:
            return
        if not chunk:
            return
        yield chunk


def arm_variables(reading: ArmReading) -> dict[str, object]:
    """The arm's reading under RTDE's output names."""
    safety = reading.safety_mode
    status_bits = 1 | (2 if reading.runtime_state == 2 else 0)  # power on, program running
    if reading.robot_mode != 7:
        status_bits &= ~1
    safety_bits = {  # 0 normal, 2 protective stop, 6-7 emergency stop, 10 stopped for safety
        SafetyMode.NORMAL: 1,
        SafetyMode.PROTECTIVE_STOP: (1 << 2) | (1 << 10),
        SafetyMode.ROBOT_EMERGENCY_STOP: (1 << 6) | (1 << 7) | (1 << 10),
    }.get(SafetyMode(safety), 0)
    return {
        "timestamp": reading.timestamp,
        "target_q": reading.target_q,
        "target_qd": reading.target_qd,
        "target_qdd": reading.target_qdd,
        "target_current": reading.current,
        "target_moment": reading.torque,
        "actual_q": reading.q,
        "actual_qd": reading.qd,
        "actual_qdd": reading.qdd,
        "actual_current": reading.current,
        "actual_current_as_torque": reading.torque,
        "actual_moment": reading.torque,
        "joint_control_output": reading.current,
        "actual_TCP_pose": reading.tcp_pose,
        "actual_TCP_speed": reading.tcp_speed,
        "actual_TCP_force": reading.tcp_force,
        "target_TCP_pose": reading.tcp_pose,
        "target_TCP_speed": reading.tcp_speed,
        "ft_raw_wrench": reading.tcp_force,
        "joint_temperatures": np.full(6, 35.0),
        "actual_joint_voltage": np.full(6, 48.0),
        "actual_execution_time": 0.2,
        "robot_mode": reading.robot_mode,
        "joint_mode": np.full(6, 253 if reading.robot_mode == 7 else 239),
        "safety_mode": safety,
        "safety_status": safety,
        "runtime_state": reading.runtime_state,
        "robot_status_bits": status_bits,
        "safety_status_bits": safety_bits,
        "speed_scaling": reading.speed_fraction,
        "target_speed_fraction": reading.speed_fraction,
        "actual_main_voltage": 48.0,
        "actual_robot_voltage": 48.0,
        "actual_robot_current": float(np.abs(reading.current).sum()),
        "actual_digital_output_bits": reading.digital_out,
        "payload": 0.0,
    }


class RTDEServer(socketserver.ThreadingTCPServer):
    """RTDE on ``address``; ``reading()`` gives the arm's newest reading."""

    allow_reuse_address = True
    daemon_threads = True

    def __init__(
        self,
        address: tuple[str, int],
        reading: Callable[[], ArmReading],
        registers: Registers,
        digital_output: Callable[[int, int], None] | None = None,
    ) -> None:
        self.reading, self.registers = reading, registers
        self.digital_output = digital_output  # (mask, bits) of the standard digital outputs
        self.running = True
        self._clients = 0
        self._clients_lock = threading.Lock()
        self.connections: set[socket.socket] = set()
        super().__init__(address, _RTDEHandler)

    def next_client(self) -> int:
        with self._clients_lock:
            self._clients += 1
            return self._clients

    def drop_connections(self) -> None:
        """Cut every RTDE connection, as a pulled network cable does."""
        for connection in list(self.connections):
            with contextlib.suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)


class _RTDEHandler(socketserver.BaseRequestHandler):
    server: RTDEServer

    def setup(self) -> None:
        self.client = self.server.next_client()
        self.request.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.send_lock = threading.Lock()
        self.output: tuple[float, list[str], str, list[type]] | None = None
        self.inputs: dict[int, tuple[list[str], str]] = {}
        self.streaming = threading.Event()
        self.server.connections.add(self.request)

    def finish(self) -> None:
        self.streaming.clear()
        self.server.connections.discard(self.request)
        self.server.registers.release(self.client)

    def send(self, kind: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.request.sendall(pack(kind, payload))

    def handle(self) -> None:
        buffer = b""
        for chunk in received(self.request):
            buffer += chunk
            while len(buffer) >= 3:
                size, kind = struct.unpack_from(">HB", buffer)
                if size < 3:
                    return  # a corrupt stream: drop the client as the controller does
                if len(buffer) < size:
                    break
                payload, buffer = buffer[3:size], buffer[size:]
                try:
                    self.dispatch(kind, payload)
                except OSError:
                    return

    def dispatch(self, kind: int, payload: bytes) -> None:
        if kind == REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self.send(kind, struct.pack(">B", version in (1, PROTOCOL_VERSION)))
        elif kind == GET_URCONTROL_VERSION:
            self.send(kind, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == SETUP_OUTPUTS:
            (frequency,) = struct.unpack(">d", payload[:8])
            names = [n for n in payload[8:].decode().split(",") if n]
            types = [VARIABLE_TYPES.get(n, "NOT_FOUND") for n in names]
            ok = "NOT_FOUND" not in types
            if ok:
                fmt = ">B" + "".join(FORMATS[t] for t in types)
                casts = [int, *_casts(types)]
                self.output = (min(max(frequency, 1.0), 500.0), names, fmt, casts)
            self.send(kind, struct.pack(">B", 1 if ok else 0) + ",".join(types).encode())
        elif kind == SETUP_INPUTS:
            self.setup_inputs([n for n in payload.decode().split(",") if n])
        elif kind == START:  # the reply goes out before the first data package
            self.send(kind, struct.pack(">B", 1))
            if self.output is not None and not self.streaming.is_set():
                self.streaming.set()
                threading.Thread(target=self.stream, daemon=True).start()
        elif kind == PAUSE:
            self.streaming.clear()
            self.send(kind, struct.pack(">B", 1))
        elif kind == DATA_PACKAGE:
            self.receive_inputs(payload)
        elif kind == TEXT_MESSAGE:
            return

    def setup_inputs(self, names: list[str]) -> None:
        registers = self.server.registers
        types = []
        with registers.lock:
            for name in names:
                kind = VARIABLE_TYPES.get(name, "NOT_FOUND")
                owner = registers.writers.get(name)
                if kind != "NOT_FOUND" and owner not in (None, self.client):
                    kind = "IN_USE"
                types.append(kind)
            ok = all(t in FORMATS for t in types)
            recipe = 0
            if ok:
                for name in names:
                    registers.writers[name] = self.client
                recipe = len(self.inputs) + 1
                self.inputs[recipe] = (names, ">" + "".join(FORMATS[t] for t in types))
        self.send(SETUP_INPUTS, struct.pack(">B", recipe) + ",".join(types).encode())

    def receive_inputs(self, payload: bytes) -> None:
        recipe = payload[0]
        if recipe not in self.inputs:
            return
        names, fmt = self.inputs[recipe]
        if len(payload) - 1 != struct.calcsize(fmt):
            return  # a package that does not fit its recipe is ignored, as the controller does
        values = struct.unpack(fmt, payload[1:])
        registers = self.server.registers
        now = time.monotonic()
        update = dict(zip(names, values, strict=True))
        with registers.lock:
            registers.values.update(update)
            registers.updated.update(dict.fromkeys(names, now))
            if registers.listener is not None:
                registers.listener(update, now)
        if "standard_digital_output_mask" in names and self.server.digital_output is not None:
            self.server.digital_output(
                int(update["standard_digital_output_mask"]), int(update["standard_digital_output"])
            )

    def stream(self) -> None:
        """Send the output recipe once per ``1 / frequency`` of the controller's clock.

        As on a controller, a package is a control cycle: each one carries a new cycle's
        reading (its ``timestamp`` a whole number of servo periods on), never the same
        one twice, however late the host wakes this thread."""
        assert self.output is not None
        frequency, names, fmt, casts = self.output
        widths = [_width(VARIABLE_TYPES[name]) for name in names]
        period = 1.0 / frequency
        registers = self.server.registers
        last: float | None = None
        while self.streaming.is_set() and self.server.running:
            reading = self.server.reading()
            if last is not None and reading.timestamp < last + period - CLOCK_TOLERANCE:
                time.sleep(min(period / 4, POLL))
                continue
            last = reading.timestamp
            variables = arm_variables(reading)
            row: list[object] = [1]
            with registers.lock:
                for name, width in zip(names, widths, strict=True):
                    value = variables.get(name)
                    if value is None:
                        value = registers.values.get(name, 0)
                    flat = np.ravel(value).tolist()
                    row.extend(flat if len(flat) == width else [0] * width)
            values = [cast(v) for cast, v in zip(casts, row, strict=True)]
            try:
                self.send(DATA_PACKAGE, struct.pack(fmt, *values))
            except OSError:
                return


def _width(kind: str) -> int:
    """How many numbers a variable of RTDE type ``kind`` packs."""
    code = FORMATS[kind]
    return int(code[:-1] or 1)


def _casts(types: list[str]) -> list[type]:
    """The Python type each packed value of a recipe with these variable types takes."""
    casts: list[type] = []
    for kind in types:
        code = FORMATS[kind][-1]
        cast = float if code == "d" else bool if code == "?" else int
        casts.extend([cast] * _width(kind))
    return casts
