"""ur_rtde's control script as the emulated controller runs it.

The real library uploads a URScript program (port 30003) whose main loop reads a
command id from ``input_int_register_0`` and its arguments from the double registers,
every control cycle. The handshake on ``output_int_register_0``: 1 ready, 2 done.
Realtime commands (servoJ, speedJ, speedL, ...) are applied every cycle and answer
ready; other commands run once, to completion (a synchronous moveJ or moveL runs over
many cycles), answer done, and wait for the client to clear the command (0). Command
255 ends the program; so do the RTDE watchdog, a protective or emergency stop, and the
dashboard's ``stop``. A path (command 45) runs the waypoints ur_rtde wrote into the
script (:mod:`.script`) one after another, each reached before the next starts (blend
radii are not modelled), each announced on the asynchronous progress register.

A realtime command is taken with the arguments of the package it came in, even when
the next package (a watchdog kick: ur_rtde sends it as command 0) overwrote the
registers before the cycle read them: the script's servo thread keeps servoing to the
newest target, and a kick means only "no new command".

In teach mode the script's motion commands run, but a UR's arm follows no trajectory
then: the emulator ignores them (the arm holds) and says so once on its error stream.

The commands with an effect here are those the driver and common ur_rtde use; any
other answers as the script does (ready or done) so that a client never
hangs, and the emulator says once, on its error stream, that it did nothing for it.
The script's stops are emulated as their names say: stopL (and speedStop after speedL,
servoStop) decelerate the tool in m/s^2, stopJ (speedStop after speedJ) the leading
joint in rad/s^2.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping

import numpy as np

from twinrl_robot.ur.emulator.arm import EmulatedArm, SafetyMode
from twinrl_robot.ur.emulator.rtde_server import Registers
from twinrl_robot.ur.emulator.script import ControlScript, Waypoint

REALTIME = {24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK = 1, 2, 3, 4
SPEEDJ, SPEEDL, SERVOJ, SERVOL = 9, 10, 11, 24
SPEED_STOP, SERVO_STOP, SET_PAYLOAD, SET_TCP = 15, 16, 17, 29
TEACH_MODE, END_TEACH_MODE = 18, 19
PROTECTIVE_STOP, STOPL, STOPJ, SET_WATCHDOG = 31, 33, 34, 35
GET_JOINT_TORQUES, GET_TCP_OFFSET, MOVE_PATH, IS_STEADY = 38, 40, 45, 47
FREEDRIVE_MODE, END_FREEDRIVE_MODE, GET_FREEDRIVE_STATUS = 52, 53, 54
GET_ACTUAL_TOOL_FLANGE_POSE, STOP_SCRIPT = 58, 255
MOVES = (MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK)
MOTIONS = {*MOVES, MOVE_PATH, SPEEDJ, SPEEDL, SERVOJ, SERVOL}
READY, DONE = 1, 2


STALL = 0.02  # s between two control cycles beyond which the emulator itself stalled


class ControlProgram:
    """The running control script (see the module docstring)."""

    def __init__(self, arm: EmulatedArm, registers: Registers) -> None:
        self.arm, self.registers = arm, registers
        self.offset = 0
        self.path: tuple[Waypoint, ...] = ()  # the waypoints written into the script
        self.executing = False
        self.pending: str | None = None  # a blocking command still under way
        self.watchdog_period: float | None = None
        self.started_at = 0.0
        # A real controller never stalls; this process can (two cores, a camera to
        # render): after the emulator's own cycle was late, the host gets a whole
        # watchdog period from then, so a stall here is never blamed on the host.
        self._previous_cycle = 0.0
        self._resumed_at = 0.0
        self.messages: list[str] = []  # what the program stopped for, newest last
        self._warned: set[int] = set()  # commands reported as not emulated
        self._latched: tuple[Mapping[str, float | int | bool], float] | None = None
        registers.listener = self._received
        self.async_move = False  # an asynchronous move (or path) is under way
        self._async_writes = 0
        self._async_id = 0
        self._waypoint: int | None = None  # the path's waypoint under way
        self._tool_speed = False  # whether the newest speed command was speedL
        self._ignored_teaching = False  # a motion in teach mode was reported

    @property
    def running(self) -> bool:
        return self.arm.program_running

    def start(self, script: ControlScript) -> None:
        """A complete script arrived: (re)start the program."""
        with self.arm.lock:
            self.offset, self.path = script.offset, script.path
            self._waypoint = None
            self.executing, self.pending, self.watchdog_period = False, None, None
            self._latched = None
            self.started_at = time.monotonic()
            if self.arm.safety_mode == SafetyMode.NORMAL and self.arm.robot_mode == 7:
                self.arm.program_running = True
                self.async_move = False
                self._write_async_progress(-1)
                self._write_int(0, READY)

    def end(self, reason: str) -> None:
        """The program stops (command 255, watchdog, dashboard ``stop``, a fault)."""
        with self.arm.lock:
            if self.arm.program_running:
                self.messages.append(reason)
            self.arm.program_running = False
            self.watchdog_period = None
            self.pending = None
            self._finish_async()
            self.arm.teaching = False  # teach mode ends with the program
            self.arm.stop()

    def _received(self, package: Mapping[str, float | int | bool], at: float) -> None:
        """An input package came (under the registers' lock): keep the newest realtime
        command with its arguments until the next cycle runs it."""
        if package.get(f"input_int_register_{self.offset}") in REALTIME:
            self._latched = (package, at)

    # ------------------------------------------------------------------ cycle
    def cycle(self, scheduled: float | None = None) -> None:
        """One control cycle of the script (called before each servo period, which was
        due at ``scheduled``, a ``time.monotonic()``: a servo target's age is counted to
        then, so a cycle that runs late does not move the target's path)."""
        now = time.monotonic()
        if now - self._previous_cycle > STALL:
            self._resumed_at = now
        self._previous_cycle = now
        if not self.running:
            return
        if self._watchdog_expired():
            self.end("the RTDE watchdog expired: no command came in time")
            return
        with self.registers.lock:
            latched, self._latched = self._latched, None
        if latched is not None:
            package, at = latched
            self._realtime(package, age=max(0.0, (now if scheduled is None else scheduled) - at))
        cmd = int(self._read_int(0))
        if cmd in MOTIONS and self.arm.teaching:
            self._ignored_in_teach_mode()
        if cmd in REALTIME:
            if latched is None:
                self._measure(cmd)  # the script repeats a realtime command every cycle
            self._write_int(0, READY)
        elif cmd == 0:
            self.executing = False
            self._write_int(0, READY)
        elif cmd == STOP_SCRIPT:
            self.end("the client stopped the control script")
        elif not self.executing:
            self.executing = True
            self._begin(cmd)
        elif self.pending is not None and self._finished():
            self.pending = None
            self._write_int(0, DONE)
        if self._waypoint is not None and self.arm.reference.idle:
            self._start_waypoint(self._waypoint + 1)
        if self.async_move and self._waypoint is None and self.arm.resting:
            self._finish_async()

    def _finish_async(self) -> None:
        """The asynchronous move ended (arrived, stopped or replaced)."""
        self._waypoint = None
        if self.async_move:
            self.async_move = False
            self._write_async_progress(-1)

    def _start_waypoint(self, index: int) -> None:
        """Start the path's waypoint ``index`` (the ones before it reached), announcing it
        on the progress register as the script's ``signal_async_progress(i)`` does."""
        if index >= len(self.path):
            self._waypoint = None
            return
        self._waypoint = index
        self._write_async_progress(index)
        waypoint, arm = self.path[index], self.arm
        target = waypoint.target
        if waypoint.kind == "movej":
            q = arm.inverse_kinematics(target) if waypoint.pose else target
            arm.move(q, speed=waypoint.speed, acceleration=waypoint.acceleration)
        else:  # movel, movep: linear in tool space
            pose = target if waypoint.pose else arm.forward_kinematics(target)
            arm.move_linear(pose, speed=waypoint.speed, acceleration=waypoint.acceleration)

    def _ignored_in_teach_mode(self) -> None:
        if not self._ignored_teaching:
            self._ignored_teaching = True
            print(
                "emulator: a motion command came in teach mode, where a UR follows no "
                "trajectory; the arm holds",
                file=sys.stderr,
                flush=True,
            )

    def _write_async_progress(self, progress: int) -> None:
        """The script's asynchronous progress word (``output_int_register_2``): bits
        24-30 the operation's id, counted up as one starts (progress 0), 16-22 a count of
        writes, 15 running, 0-14 the progress; a negative progress: finished."""
        self._async_writes = (self._async_writes + 1) % 128
        if progress == 0:
            self._async_id = (self._async_id + 1) % 128
        word = self._async_id << 24 | self._async_writes << 16
        if progress >= 0:
            word |= 1 << 15 | min(progress, (1 << 15) - 1)
        self._write_int(2, word)

    def _watchdog_expired(self) -> bool:
        if self.watchdog_period is None:
            return False
        name = f"input_int_register_{self.offset}"
        last = max(self.registers.updated.get(name, self.started_at), self._resumed_at)
        return time.monotonic() - last > self.watchdog_period

    def _realtime(self, package: Mapping[str, float | int | bool], age: float) -> None:
        """Run the realtime command of ``package``, which came ``age`` s ago."""
        offset = self.offset

        def doubles(start: int, count: int) -> np.ndarray:
            names = [f"input_double_register_{start + i + offset}" for i in range(count)]
            return np.array([float(package.get(n, self.registers.get(n))) for n in names])

        cmd = int(package[f"input_int_register_{offset}"])
        if cmd in (SERVOJ, SERVOL, SPEEDJ, SPEEDL):  # an asynchronous move gives way
            self._finish_async()
        if cmd in (SERVOJ, SERVOL):
            # doubles: target, speed, acceleration (both unused), time, lookahead, gain
            duration, lookahead, gain = doubles(8, 3)
            servo = self.arm.servo if cmd == SERVOJ else self.arm.servo_pose
            servo(doubles(0, 6), duration, age, lookahead, gain)
        elif cmd in (SPEEDJ, SPEEDL):  # doubles: speeds, acceleration, time (unused)
            self._tool_speed = cmd == SPEEDL
            speed = self.arm.speed_tool if self._tool_speed else self.arm.speed
            speed(doubles(0, 6), max(doubles(6, 1)[0], 1e-3))
        else:
            self._measure(cmd)

    def _measure(self, cmd: int) -> None:
        """The realtime commands that read the arm (answered afresh every cycle)."""
        arm = self.arm
        if cmd == GET_JOINT_TORQUES:
            self._write_doubles(0, arm.read().torque)
        elif cmd == GET_ACTUAL_TOOL_FLANGE_POSE:
            with arm.lock:  # the tool frame's scratch state is shared with the readers
                self._write_doubles(0, arm.tool.pose(arm.cell.arm_q, tool=False))
        elif cmd not in (SERVOJ, SERVOL, SPEEDJ, SPEEDL):
            self._not_emulated(cmd)

    def _begin(self, cmd: int) -> None:
        """Start a non-realtime command; it answers done now or when :meth:`_finished`."""
        arm = self.arm
        if cmd in (*MOVES, MOVE_PATH):
            self._finish_async()  # the script's stop_async_move()
            synchronous = self._read_int(1) == 0
            if not synchronous:
                self.async_move = True
                self._write_async_progress(0)
            self._move(cmd)
            if synchronous:  # done when the arm arrives
                self.pending = "move"
                return
        elif cmd in (SERVO_STOP, SPEED_STOP, STOPJ, STOPL):
            self._waypoint = None
            deceleration = max(self._double(0), 1e-3)
            if cmd == STOPJ or (cmd == SPEED_STOP and not self._tool_speed):
                arm.stop(deceleration)
            else:  # the script's stopl
                arm.stop_tool(deceleration)
            if not (cmd in (STOPJ, STOPL) and self._read_int(1) == 1):
                self.pending = "stop"
                return
        elif cmd in (TEACH_MODE, FREEDRIVE_MODE, END_TEACH_MODE, END_FREEDRIVE_MODE):
            arm.teach(cmd in (TEACH_MODE, FREEDRIVE_MODE))
            self._ignored_teaching = False
        elif cmd == GET_FREEDRIVE_STATUS:
            self._write_int(1, int(arm.teaching))
        elif cmd == SET_WATCHDOG:
            frequency = self._double(0)
            self.watchdog_period = 1.0 / frequency if frequency > 0 else None
        elif cmd == PROTECTIVE_STOP:
            arm.protective_stop()
            self.end("a protective stop was triggered")
            return
        elif cmd == SET_TCP:
            arm.tool.set_offset(self._doubles(0, 6))
        elif cmd == GET_TCP_OFFSET:
            self._write_doubles(0, arm.tool.offset)
        elif cmd == IS_STEADY:
            self._write_int(1, int(float(np.abs(arm.read().qd).max()) < 1e-3))
        elif cmd != SET_PAYLOAD:  # the plant's payload is a hidden effect: just accepted
            self._not_emulated(cmd)
        self._write_int(0, DONE)

    def _move(self, cmd: int) -> None:
        """Start moveJ, moveJ_IK, moveL, moveL_FK (target, speed, acceleration in the
        doubles) or the script's path."""
        if cmd == MOVE_PATH:
            self._start_waypoint(0)
            return
        arm, target = self.arm, self._doubles(0, 6)
        speed, acceleration = self._double(6), self._double(7)
        if cmd == MOVEJ_IK:
            target = arm.inverse_kinematics(target)
        elif cmd == MOVEL_FK:
            target = arm.forward_kinematics(target)
        move = arm.move if cmd in (MOVEJ, MOVEJ_IK) else arm.move_linear
        move(target, speed=speed, acceleration=acceleration)

    def _not_emulated(self, cmd: int) -> None:
        if cmd not in self._warned:
            self._warned.add(cmd)
            print(
                f"emulator: ur_rtde command {cmd} is not emulated; it is answered without "
                "moving or measuring anything",
                file=sys.stderr,
                flush=True,
            )

    def _finished(self) -> bool:
        if self.pending in ("move", "stop"):  # done when the arm has arrived and settled
            return self._waypoint is None and self.arm.resting
        return True

    # -------------------------------------------------------------- registers
    def _read_int(self, index: int) -> int:
        return int(self.registers.get(f"input_int_register_{index + self.offset}"))

    def _double(self, index: int) -> float:
        return float(self.registers.get(f"input_double_register_{index + self.offset}"))

    def _doubles(self, start: int, count: int) -> np.ndarray:
        return np.array([self._double(start + i) for i in range(count)])

    def _write_int(self, index: int, value: int) -> None:
        self.registers.set(f"output_int_register_{index + self.offset}", value)

    def _write_doubles(self, start: int, values: np.ndarray) -> None:
        for i, value in enumerate(np.asarray(values, float)):
            self.registers.set(f"output_double_register_{start + i + self.offset}", float(value))
