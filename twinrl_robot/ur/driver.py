"""A Universal Robots arm behind the :class:`~twinrl_robot.robot.Robot` protocol.

It talks to the controller through ur_rtde's own ``RTDEControlInterface`` and
``RTDEReceiveInterface``, held in a process of their own by a
:class:`~twinrl_robot.ur.controller_link.ControllerLink` (and ``DashboardClient`` to
explain a stop). An episode's 7-D
action goes through the twin's IK (the same :class:`~twinrl_sim.control.EndEffectorController`
the twin and the plant use, so the twin and the arm execute the same joint targets),
then the :class:`~twinrl_robot.guard.JointGuard`, then the
:class:`~twinrl_robot.ur.servo.ServoStream` that sends it at the controller's rate: with
servoJ, or (``servo: servol`` in the cell file) as the pose of the controller's TCP with
servoL, the controller solving the inverse kinematics.
``act`` returns at the end of the control period, so the loop above keeps the rate.

Faults are checked at every step and by the stream at every servo period: a protective
stop, an emergency stop, a program that stopped (the watchdog, the pendant, the
controller leaving remote control) or a lost connection raises :class:`RobotStopped`
with one line saying what happened and how to recover; from then on nothing is sent
until :meth:`URArm.acknowledge`, which after a lost connection connects afresh.

What is real-cell honest here: observations are the controller's measured joints, the
TCP from the twin's kinematics of those joints (the contract's frame), the gripper's own
reading and the joint torques the controller applies (RTDE ``target_moment``). Nothing
reads object poses: on a real cell ``privileged`` is ``None``; an emulated cell may lend
its ground truth (:mod:`.emulator.harness`) for tests and scripted experts, and says so.
"""

from __future__ import annotations

import contextlib
import socket
import time
from collections.abc import Callable

import numpy as np

from twinrl_data.schema import (
    CONTROLLER_TARGET,
    CONTROLLER_TIME,
    CONTROLLER_TIME_NAMES,
    EFFORT,
    ENVIRONMENT_STATE,
    JOINT_TARGET,
    STATE,
    WRENCH,
    WRENCH_NAMES,
    effort_names,
)
from twinrl_robot.cell_file import CellFile
from twinrl_robot.errors import RobotError
from twinrl_robot.guard import GuardLimits, JointGuard
from twinrl_robot.realtime import check_realtime
from twinrl_robot.robot import Privileged, Sent
from twinrl_robot.tool_clearance import tool_points
from twinrl_robot.ur.cameras import CameraRig
from twinrl_robot.ur.controller_link import (
    ControllerHealth,
    ControllerLink,
    ControllerRefused,
    LinkLost,
)
from twinrl_robot.ur.gripper import Gripper, NoGripper
from twinrl_robot.ur.sensor_streams import SensorStreams
from twinrl_robot.ur.servo import MIN_SEGMENT
from twinrl_robot.ur.tool_frame import ToolFrame
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.control import EndEffectorController, IKSettings
from twinrl_sim.robots.ur5e import JOINT_SPEED_LIMIT
from twinrl_sim.tasks import Task, TaskConfig

RTDE_PORT = 30004
CONNECT_TIMEOUT = 3.0  # s to reach the controller before saying it is unreachable
RESET_SPEED, RESET_ACCELERATION = 0.6, 1.2  # rad/s, rad/s^2 of the move to a start pose
SERVO_STOP_DECELERATION = 10.0  # rad/s^2
ARRIVED = 2e-3  # rad from a move's goal that counts as there
MOVE_STALL = 2.0  # s without getting ARRIVED nearer its goal that ends a move
RELEASE_TIMEOUT = 2.0  # s for a cleared stop to show in the controller's state
EMERGENCY_STOP = (
    "the emergency stop is pressed; release it, power the arm on and release the brakes on "
    "the pendant, then acknowledge"
)
PROTECTIVE_STOP = (
    "the arm is in a protective stop (it hit something or exceeded a limit); inspect the "
    "cell, unlock it on the pendant, then acknowledge"
)
LEFT_REMOTE = (
    "the controller left remote control; switch the pendant back to Remote Control, then "
    "acknowledge"
)
PROGRAM_STOPPED = (
    "the control program on the controller stopped (watchdog: the host stopped sending, or "
    "stopped from the pendant); acknowledge to start it again"
)
Arrange = Callable[[TaskConfig], None]
"""Sets a configuration's objects up in the cell (a person guided by the twin; the
emulator's harness in tests); the arm is already at its start pose."""


class RobotConnectionError(RobotError):
    """The controller cannot be reached or refuses the connection."""


class RobotStopped(RobotError):
    """The arm stopped for a reason outside the program (see the message)."""


class URArm:
    """A UR arm on a real (or emulated) controller, driven like a robot.

    Args:
        cell: the cell file (host, rates, safety limits).
        task: the task, whose scene is the cell's twin (kinematics and start pose).
        gripper: the gripper (default: none).
        cameras: the cell's cameras, matched to control steps.
        arrange: sets a configuration's objects up at each reset (``None``: the person
            does it before the episode starts; the arm only goes to its start pose).
        effort: report joint torques (``observation.effort``) and the TCP's force and
            torque (``observation.wrench``), as the controller measures them.
        privileged: the ground truth of an emulated cell (never of a real one).
    """

    world = "real"

    def __init__(
        self,
        cell: CellFile,
        task: Task,
        *,
        gripper: Gripper | None = None,
        cameras: CameraRig | None = None,
        arrange: Arrange | None = None,
        effort: bool = True,
        privileged: Privileged | None = None,
    ) -> None:
        self.cell, self.task = cell, task
        self.host = cell.arm.host
        self.control_hz = cell.arm.control_hz
        self.servo_hz = cell.arm.servo_rate
        self.gripper = gripper or NoGripper()
        self.cameras = cameras or CameraRig([])
        self.arrange, self.effort, self.privileged = arrange, effort, privileged
        twin = Cell(compile_scene(task.scene))
        self.twin = twin  # the twin's model: kinematics, start pose, names
        safety = cell.safety
        settings = IKSettings(
            joint_margin=safety.joint_margin, max_joint_speed=safety.max_joint_speed
        )
        workspace = (np.array(safety.workspace.low), np.array(safety.workspace.high))
        self.kinematics = EndEffectorController(
            twin.model, twin.layout, workspace, 1.0 / self.control_hz, settings
        )
        self.guard = JointGuard(
            GuardLimits(
                q_low=self.kinematics.q_low,
                q_high=self.kinematics.q_high,
                max_speed=safety.max_joint_speed,
                max_acceleration=safety.max_joint_acceleration,
                box_low=workspace[0],
                box_high=workspace[1],
                cone_deg=safety.tool_cone_deg,
                tool_points=tool_points(twin),
                table_top=twin.table_top,
                table_clearance=safety.table_clearance,
                approach_height=safety.table_approach_height,
                approach_speed=safety.table_approach_speed,
            ),
            self.kinematics.forward,
            1.0 / self.control_hz,
        )
        self.names = twin.contract_names()
        self.names.pop(ENVIRONMENT_STATE, None)
        if effort:  # what the controller reports of forces: joint torques, the TCP wrench
            self.names[EFFORT] = effort_names(twin.layout.arm_joints)
            self.names[WRENCH] = list(WRENCH_NAMES)
        self.names[CONTROLLER_TIME] = list(CONTROLLER_TIME_NAMES)
        self.names[CONTROLLER_TARGET] = list(self.names[JOINT_TARGET])
        self.start_q = np.array(twin.layout.home_qpos, float)
        self.fault: str | None = None
        self._clock_at_reset = 0.0  # s, the controller's clock when the episode began
        self._counts_at_reset: dict[str, dict[str, int]] = {}
        tool = ToolFrame(
            twin.model, twin.layout.flange_body, twin.layout.arm_joints, cell.arm.tcp_offset
        )
        # The loop's thread takes it at each episode: refused here, before the arm moves.
        self.loop_priority = cell.arm.realtime_priority
        check_realtime(self.loop_priority)
        # A late servo period is caught up at the fastest a segment runs (within the
        # joints' top speed), not in a jump.
        self._link = ControllerLink(
            self.host,
            self.servo_hz,
            tool if cell.arm.servo == "servol" else None,
            max_speed=min(safety.max_joint_speed / MIN_SEGMENT, JOINT_SPEED_LIMIT),
        )
        self._receive, self._control, self.stream = (
            self._link.receive,
            self._link.control,
            self._link.stream,
        )
        _connect(self._link)  # the stream kicks the watchdog from here on
        self._apply_cell_settings()
        self._next_step: float | None = None
        self._opening = 0.0  # the gripper's opening at the last observation
        # When the newest observation was taken, on the host's clock as the samples are
        # stamped: its controller package's time, or its frames' if later (``observe``);
        # None before the first one.
        self.observed_at: float | None = None
        self._stream_kinematics = EndEffectorController(  # its own data: another thread's
            twin.model, twin.layout, workspace, 1.0 / self.control_hz, settings
        )
        self.sensors = SensorStreams(
            self.cameras, self._receive, self.servo_hz, self._state_of, self.names[STATE]
        )

    # ---------------------------------------------------------------- episode
    def reset(self, config: TaskConfig | dict) -> dict[str, np.ndarray]:
        """Bring the arm to the start pose, have the configuration set up, start servoing."""
        self._check()
        config = TaskConfig.from_dict(config)
        self.stream.stop()
        self.guard.check_start(self.start_q, "the task's start pose")
        self._move_to(self.start_q)
        self.gripper.command(0.0)
        if self.arrange is not None:
            self.arrange(config)
        q = self.measured_q()
        self.guard.reset(q)
        self.kinematics.reset(q)
        self._counts_at_reset = self.cameras.counts()
        self._clock_at_reset = float(self._receive.getTimestamp())
        self.stream.start(q)
        self._next_step = time.monotonic() + 1.0 / self.control_hz
        return self.observe()

    def _move_to(self, q: np.ndarray) -> None:
        """moveJ to ``q``, asynchronously (the stream's thread keeps kicking the watchdog).
        A slow move is waited for (the pendant's speed slider, a controller behind real
        time); one that stops getting nearer for :data:`MOVE_STALL` s is stopped."""
        if not self._control.moveJ(q.tolist(), RESET_SPEED, RESET_ACCELERATION, True):
            self._check(refused="the controller refused the move to the start pose")
        nearest, progressed = np.inf, time.monotonic()
        while True:
            self._check()
            remaining = float(np.abs(self.measured_q() - q).max())
            if remaining < ARRIVED and np.abs(self._receive.getActualQd()).max() < 1e-2:
                return
            if remaining < nearest - ARRIVED:
                nearest, progressed = remaining, time.monotonic()
            elif time.monotonic() - progressed > MOVE_STALL:
                self._control.stopJ(SERVO_STOP_DECELERATION)
                raise RobotStopped(
                    f"the arm stopped {1000 * remaining:.1f} mrad short of the start pose "
                    f"(no nearer for {MOVE_STALL:g} s); check for an obstacle in its way"
                )
            time.sleep(0.01)

    def act(self, action: np.ndarray) -> Sent:
        self._check()
        action = np.asarray(action, np.float32)
        target = self.kinematics.joint_targets(action, self.measured_q())
        return self._send(target, float(action[6]), action)

    def servo_joints(self, joint_target: np.ndarray, gripper: float) -> Sent:
        """Hold joint targets for one control period (replay, excitation), guarded."""
        self._check()
        sent = self._send(np.asarray(joint_target, float), gripper, np.zeros(7, np.float32))
        self.kinematics.reset(sent.joint_target)
        return sent

    def hold(self) -> None:
        q = self.measured_q()
        self.stream.hold(q)
        self.kinematics.reset(q)
        self.guard.anchor(q)

    def observe(self) -> dict[str, np.ndarray]:
        self._check()
        getters = ("getTimestamp", "getActualQ", "getActualQd", "getTargetQ")
        if self.effort:  # the torques the controller applies (RTDE target_moment)
            getters += ("getTargetMoment", "getActualTCPForce")
        clock, q, qd, target, *forces = self._link.snapshot(getters)
        self.sensors.saw(clock, time.monotonic())
        q, qd = np.array(q), np.array(qd)
        position, quat = self.kinematics.forward(q)
        self._opening = self.gripper.opening()
        state = np.concatenate([q, qd, position, quat, [self._opening]])
        observation = {
            "observation.state": state.astype(np.float32),
            CONTROLLER_TIME: np.array([clock - self._clock_at_reset], np.float32),
            CONTROLLER_TARGET: np.array(target, np.float32),
        }
        if self.effort:
            observation[EFFORT] = np.array(forces[0], np.float32)
            observation[WRENCH] = np.array(forces[1], np.float32)
        observation.update(self.cameras.images())
        # The step is logged at its package's time on the samples' clock, not when the
        # host got round to it (the gripper's socket and the cameras come after), so a
        # step and the 500 Hz state line up however loaded the host is; or at its
        # frames' capture if later, as a live episode gives each step the newest frame
        # captured by its time, which must be the frame read here.
        package_at = clock + self.sensors.offset
        captured = self.cameras.captured_at
        self.observed_at = package_at if captured is None else max(package_at, captured)
        return observation

    def _state_of(self, joints: np.ndarray, speeds: np.ndarray) -> np.ndarray:
        """The observation's state of controller packages (see ``observe``)."""
        poses = [np.concatenate(self._stream_kinematics.forward(q)) for q in joints]
        opening = np.full((len(joints), 1), self._opening)
        return np.hstack([joints, speeds, np.array(poses).reshape(-1, 7), opening]).astype(
            np.float32
        )

    def sensor_streams(self) -> SensorStreams:
        """The cameras' every frame and the controller's every package, for a live episode."""
        self.sensors.rig = self.cameras  # the cameras are opened after the arm
        return self.sensors

    def sensor_counts(self) -> dict[str, dict[str, int]]:
        """Per camera, frames delivered, dropped and stale since the last reset (what an
        episode's metadata records, so that no repeated frame goes unnoticed)."""
        now, before = self.cameras.counts(), self._counts_at_reset
        return {
            name: {k: v - before.get(name, {}).get(k, 0) for k, v in counts.items()}
            for name, counts in now.items()
        }

    def close(self) -> None:
        self.stream.close()
        try:
            with contextlib.suppress(LinkLost, RuntimeError):  # gone: nothing left to stop
                if self._control.isProgramRunning():
                    self._control.servoStop(SERVO_STOP_DECELERATION)
                    self._control.stopScript()
        finally:
            self._link.close()
            self.gripper.close()
            self.cameras.close()
            close_truth = getattr(self.privileged, "close", None)
            if close_truth is not None:
                close_truth()

    # ------------------------------------------------------------------ faults
    def acknowledge(self) -> None:
        """The person has cleared the stop: check the arm is ready and restart the
        control program; until then every command raises :class:`RobotStopped`. After a
        lost connection it connects afresh (:class:`RobotConnectionError` while the
        controller cannot be reached)."""
        if not self._link.health().connected:
            self._link.close()
            _connect(self._link)
            self._apply_cell_settings()
            self.fault = None
            return
        deadline = time.monotonic() + RELEASE_TIMEOUT  # a released stop takes a moment
        while (reason := self._stop_reason(self._link.health())) and "program" not in reason:
            if time.monotonic() > deadline:
                raise RobotStopped(reason)
            time.sleep(0.02)
        restart = not self._control.isProgramRunning()
        if restart:
            self._control.reuploadScript()
            deadline = time.monotonic() + 5.0
            while not self._control.isProgramRunning():
                if time.monotonic() > deadline:
                    raise RobotStopped(
                        "the control program did not start again on the controller; check the "
                        "pendant for a popup and that it is in Remote Control"
                    )
                time.sleep(0.01)
        self.stream.resume()  # kicking before the watchdog is set again
        if restart:
            self._apply_cell_settings()  # a new program has no watchdog, TCP or payload yet
        self.fault = None

    def _check(self, refused: str | None = None) -> None:
        if self.fault is None:
            health = self._link.health()
            reason = self._stop_reason(health)
            if not reason and (health.stream_fault or refused):
                # The controller refused a command before its published state shows why
                # (the receive interface lags the control interface by a packet or two):
                # its dashboard says at once whether the pendant or a stop is the cause.
                cause = "" if health.stream_connection_failed else self._dashboard_cause()
                reason = cause or health.stream_fault or refused or ""
            if reason:
                self.stream.silence()
                self.fault = reason
        if self.fault is not None:
            raise RobotStopped(self.fault)

    def _stop_reason(self, health: ControllerHealth) -> str:
        """Why the arm cannot be commanded, as ``health`` says, in one line, or ``""``."""
        if not health.connected:
            return (
                f"lost the connection to the controller at {self.host}; check the network "
                "cable and the controller, then acknowledge to reconnect"
            )
        if health.emergency_stopped:
            return EMERGENCY_STOP
        if health.protective_stopped:
            return PROTECTIVE_STOP
        if health.runtime_state != 2:
            return self._dashboard_cause() or PROGRAM_STOPPED
        return ""

    def _dashboard_cause(self) -> str:
        """What the dashboard says stopped the arm (``""``: nothing it knows of, or it
        cannot be asked)."""
        status = _dashboard_status(self.host)
        if status is None:
            return ""
        remote, safety = status
        if not remote:
            return LEFT_REMOTE
        safety = safety.upper()
        if "EMERGENCY" in safety:
            return EMERGENCY_STOP
        if "PROTECTIVE" in safety:
            return PROTECTIVE_STOP
        return ""

    # ------------------------------------------------------------------ inside
    def _send(self, target: np.ndarray, gripper: float, action: np.ndarray) -> Sent:
        guarded = self.guard(target)
        self.gripper.command(float(np.clip(gripper, 0.0, 1.0)))
        period = 1.0 / self.control_hz
        end = self._period_end(period)
        # The segment ends with the control period, when the next observation is taken,
        # as the twin's servos reach each target: the arm's lag is then the controller's
        # own, not however long this step took the host.
        self.stream.push(guarded.q, period, end)
        time.sleep(max(0.0, end - time.monotonic()))
        self._check()
        return Sent(action=action, joint_target=guarded.q.astype(np.float32))

    def _period_end(self, period: float) -> float:
        """When this control period ends; the next one is booked to end a period later."""
        now = time.monotonic()
        if self._next_step is None or now - self._next_step > period:
            self._next_step = now + period  # late by a whole period: start over, no burst
        end = self._next_step
        self._next_step = end + period
        return end

    def measured_q(self) -> np.ndarray:
        """The arm's joint positions (rad) as the controller measures them."""
        return np.array(self._receive.getActualQ(), float)

    def controller_target_q(self) -> np.ndarray:
        """The joint targets (rad) the controller is tracking now (its ``target_q``): how
        far the servo stream's latest target has got."""
        return np.array(self._receive.getTargetQ(), float)

    def _apply_cell_settings(self) -> None:
        arm = self.cell.arm
        self._control.setTcp(list(arm.tcp_offset))
        self._control.setPayload(arm.payload.mass, list(arm.payload.cog))
        watchdog_hz = 1000.0 / self.cell.safety.watchdog_ms  # trips after watchdog_ms of silence
        self._control.setWatchdog(watchdog_hz)

    def __repr__(self) -> str:
        return f"URArm({self.cell.arm.model} at {self.host})"


def require_reachable(host: str) -> None:
    """Refuse, in one line, a controller whose RTDE port does not answer."""
    try:
        with socket.create_connection((host, RTDE_PORT), timeout=CONNECT_TIMEOUT):
            pass
    except OSError as err:
        raise RobotConnectionError(
            f"cannot reach the UR controller at {host}:{RTDE_PORT} ({err.strerror or err}); "
            "check that the arm is powered, the cell file's `host`, and the network"
        ) from None


def _connect(link: ControllerLink) -> None:
    """Open ``link`` (ur_rtde's interfaces and the servo stream), or one line on why not."""
    require_reachable(link.host)
    try:
        link.open()
    except ControllerRefused as err:
        raise RobotConnectionError(str(err)) from None


def _dashboard_status(host: str) -> tuple[bool, str] | None:
    """Whether the controller's dashboard says it is in remote control, and its safety
    status (``None`` when the dashboard cannot be asked)."""
    import dashboard_client

    dashboard = dashboard_client.DashboardClient(host)
    try:
        dashboard.connect()
        return bool(dashboard.isInRemoteControl()), str(dashboard.safetystatus())
    except RuntimeError:
        return None
    finally:
        dashboard.disconnect()
