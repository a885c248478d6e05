"""The emulated arm: the plant's MuJoCo cell stepped at a UR controller's servo rate.

It executes what a controller program asks (servo targets, joint and tool speeds, joint
and linear moves, stops, teach mode) one servo period at a time, raises a protective
stop when the arm hits the table or presses on it harder than a UR's force limit, and
reads back what the controller publishes (joint positions, speeds, torques, the TCP pose
of the configured tool, modes).
Nothing here knows about sockets: :mod:`.server` drives it from the protocols.
"""

from __future__ import annotations

import enum
import sys
import threading
from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_robot.ur.emulator.reference import (
    SERVO_GAIN,
    SERVO_LOOKAHEAD,
    JointLimits,
    JointReference,
)
from twinrl_robot.ur.tool_frame import ToolFrame
from twinrl_sim.body_tree import subtree
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.layout import MOUNT_BODY
from twinrl_sim.robots.ur5e import JOINT_SPEED_LIMIT
from twinrl_sim.tasks import Task, TaskConfig


class RobotMode(enum.IntEnum):
    """UR robot modes (what ``robot_mode`` reports)."""

    POWER_OFF = 3
    IDLE = 5
    RUNNING = 7


class SafetyMode(enum.IntEnum):
    """UR safety modes (what ``safety_mode`` reports)."""

    NORMAL = 1
    PROTECTIVE_STOP = 3
    ROBOT_EMERGENCY_STOP = 7


class RuntimeState(enum.IntEnum):
    """UR program states (what ``runtime_state`` reports)."""

    STOPPED = 1
    PLAYING = 2


PROTECTIVE_FORCE = 150.0  # N between the robot and the table: a UR's default force limit
JOINT_ACCELERATION_LIMIT = 40.0  # rad/s^2: ur_rtde's bound on a joint's acceleration
# A stopped program (ur_rtde's stopScript, the watchdog, the dashboard's stop) brings the
# joints to rest along their path, as a UR's controlled stop does: the leading joint
# decelerates at STOP_DECELERATION, or faster where that would take longer than
# STOP_TIME, so the arm rests within STOP_TIME of the stop from any speed (from the top
# speed that is 35 rad/s^2, within the acceleration limit).
STOP_DECELERATION = 15.0  # rad/s^2
STOP_TIME = 0.09  # s
SPEED_MARGIN = 1.05  # the safety system's speed limit over the joints' top speed


@dataclass(frozen=True)
class ArmReading:
    """What the controller publishes each servo period (SI units, base frame)."""

    timestamp: float
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    target_q: np.ndarray
    target_qd: np.ndarray
    target_qdd: np.ndarray
    torque: np.ndarray  # N m the joints' servos apply
    current: np.ndarray  # A, torque over a nominal torque constant
    tcp_pose: np.ndarray  # x y z (m), rx ry rz (axis-angle, rad) of the configured TCP
    tcp_speed: np.ndarray
    tcp_force: np.ndarray  # N, N m at the TCP from the table and objects
    robot_mode: int
    safety_mode: int
    runtime_state: int
    gripper_position: float  # 0 open .. 1 closed (commanded)
    gripper_opening: float  # m, measured
    digital_out: int
    speed_fraction: float  # the pendant's speed slider, 0..1


class EmulatedArm:
    """The plant's cell of ``task`` as a UR controller runs it.

    Args:
        task: the task whose cell (scene) the arm stands in.
        effects: the plant's hidden effects compiled into the cell.
        servo_hz: the controller's servo rate (a whole number of physics steps).
        tcp_offset: the TCP configured on the controller (m, axis-angle rad, flange frame).
        torque_constant: N m per A, to report currents as a UR does.
        gripper_output: the digital output that closes a switched gripper (``None``: the
            gripper follows the Robotiq socket's position).
    """

    def __init__(
        self,
        task: Task,
        *,
        effects: dict | None = None,
        servo_hz: float = 500.0,
        tcp_offset: tuple[float, ...] = (0.0,) * 6,
        torque_constant: float = 10.0,
        gripper_output: int | None = None,
    ) -> None:
        self.task = task
        # A UR's joint servos are stiff and damp the speed error, not the speed: the
        # plant's servos are the twin's tracking ones (twinrl_sim.servo), stepped here at
        # the servo rate, so a fast stream does not saturate the wrists, a stopped one
        # halts the arm at once, and a twin can model the arm.
        physics = task.scene.physics.model_copy(update={"servo": "track"})
        scene = task.scene.model_copy(update={"physics": physics})
        self.cell = Cell(compile_scene(scene, extra_effects=effects or None))
        model = self.cell.model
        steps = model.opt.timestep * servo_hz
        self.physics_per_tick = max(1, round(1.0 / steps))
        self.period = self.physics_per_tick * model.opt.timestep
        self.lock = threading.RLock()
        self.tool = ToolFrame(
            model, self.cell.layout.flange_body, self.cell.layout.arm_joints, tcp_offset
        )
        self.torque_constant = torque_constant
        self.gripper_output = gripper_output
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.speed_fraction = 1.0  # the pendant's speed slider: scales moves' speed
        self.program_running = False
        self.teaching = False  # teach (freedrive) mode: back-drivable, no trajectories
        self.digital_out = 0
        self.gripper_position = 0.0
        self.ticks = 0
        self.fault: str | None = None  # what the newest protective stop was for
        self._lead = self.cell.servo_lead or 0.0  # s of velocity feed-forward
        self._flange = model.body(self.cell.layout.flange_body).id
        self._base = model.body(MOUNT_BODY).id
        self._table = model.geom(self.cell.layout.table_geom).id
        self._robot_bodies = subtree(model, self._base)
        self._tool_bodies = subtree(model, self._flange)
        self._arm_link_bodies = self._robot_bodies - self._tool_bodies
        self._tracker = task.start(self.cell, task.sample_config(np.random.default_rng(0)))
        joints = [model.joint(name).id for name in self.cell.layout.arm_joints]
        self.limits = JointLimits(
            lower=model.jnt_range[joints, 0].copy(),
            upper=model.jnt_range[joints, 1].copy(),
            speed=JOINT_SPEED_LIMIT,
            acceleration=JOINT_ACCELERATION_LIMIT,
        )
        # The arm powers up at rest at the twin's home.
        self.reference = JointReference(self.cell.arm_q, self.limits, self.period, self.tool)

    # -------------------------------------------------------------- commands
    def servo_pose(
        self,
        pose: np.ndarray,
        duration: float = 0.0,
        age: float = 0.0,
        lookahead: float = SERVO_LOOKAHEAD,
        gain: float = SERVO_GAIN,
    ) -> None:
        """servoL: track the TCP pose ``pose`` (the controller's inverse kinematics)."""
        with self.lock:
            target = self.reference.servo_target
            start = self.reference.q if target is None else target
            self.servo(self.tool.solve(pose, start), duration, age, lookahead, gain)

    def servo(
        self,
        q: np.ndarray,
        duration: float = 0.0,
        age: float = 0.0,
        lookahead: float = SERVO_LOOKAHEAD,
        gain: float = SERVO_GAIN,
    ) -> None:
        """servoJ: reach ``q`` ``duration`` s (at least one servo period) after it came,
        ``age`` s ago (the newest target wins), smoothed as ``lookahead`` (s) and
        ``gain`` say."""
        with self.lock:
            if self._may_move() and self._within_range(q, "servo target"):
                self.reference.servo(q, duration, age, lookahead, gain)

    def speed(self, qd: np.ndarray, acceleration: float) -> None:
        """speedJ: run the joints at ``qd`` (rad/s), reached at ``acceleration``."""
        with self.lock:
            if self._may_move():
                self.reference.speed(qd, acceleration)

    def move(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        """moveJ: go to ``q`` with a joint-space trapezoidal profile."""
        with self.lock:
            if self._may_move() and self._within_range(q, "move target"):
                self.reference.move(q, speed, acceleration)

    def move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None:
        """moveL: the TCP to ``pose`` along a straight line, at ``speed`` (m/s) and
        ``acceleration`` (m/s^2). A joint that would leave its range on the way is a
        protective stop when it gets there."""
        with self.lock:
            if self._may_move():
                self.reference.move_linear(pose, speed, acceleration)

    def speed_tool(self, twist: np.ndarray, acceleration: float) -> None:
        """speedL: run the tool at ``twist`` (m/s, rad/s; base frame), reached at
        ``acceleration`` (m/s^2)."""
        with self.lock:
            if self._may_move():
                self.reference.speed_tool(twist, acceleration)

    def stop_tool(self, deceleration: float) -> None:
        """stopL: bring the tool to rest along its line at ``deceleration`` (m/s^2)."""
        with self.lock:
            self.reference.stop_tool(deceleration)

    def inverse_kinematics(self, pose: np.ndarray) -> np.ndarray:
        """Joint positions near the reference's that put the TCP at ``pose``."""
        with self.lock:
            return self.tool.solve(pose, self.reference.q)

    def forward_kinematics(self, q: np.ndarray) -> np.ndarray:
        """The TCP pose of joint positions ``q``."""
        with self.lock:
            return self.tool.pose(q)

    def teach(self, on: bool) -> None:
        """Enter or leave teach mode. A UR's arm then gives way to a hand and follows no
        trajectory; here nobody pushes it, so it holds where it is (braking first if it
        was moving) and refuses motion until teach mode ends."""
        with self.lock:
            if on and not self.teaching:
                self.reference.stop(self.limits.acceleration)
            self.teaching = on

    def stop(self, deceleration: float | None = None) -> None:
        """Bring the joints to rest along their path at ``deceleration`` (rad/s^2 of the
        leading joint; ``None``: a stopped program's, see :data:`STOP_TIME`)."""
        with self.lock:
            if deceleration is None:
                lead = float(np.abs(self.reference.qd).max())
                deceleration = max(STOP_DECELERATION, lead / STOP_TIME)
            self.reference.stop(deceleration)

    @property
    def resting(self) -> bool:
        """Whether nothing is commanded and the joints have come to rest."""
        speed = float(np.abs(self.cell.data.qvel[self.cell.arm_dof]).max())
        return self.reference.idle and speed < 1e-2

    def set_speed_fraction(self, fraction: float) -> None:
        """The pendant's speed slider (0..1): moves run at that share of their speed."""
        with self.lock:
            self.speed_fraction = float(fraction)

    def set_digital_outputs(self, mask: int, bits: int) -> None:
        """The standard digital outputs under ``mask`` take ``bits`` (RTDE's I/O recipe)."""
        with self.lock:
            self.digital_out = (self.digital_out & ~mask) | (bits & mask)

    def _may_move(self) -> bool:
        return (
            self.safety_mode == SafetyMode.NORMAL
            and self.robot_mode == RobotMode.RUNNING
            and not self.teaching
        )

    # ----------------------------------------------------------------- faults
    def protective_stop(self, reason: str = "a protective stop was triggered") -> None:
        """Stop at once (the arm hit something, or was told to) and lock until unlocked."""
        with self.lock:
            self._lock_out(reason)
            self._halt()

    def limit_stop(self, reason: str) -> None:
        """A protective stop for a breached joint limit: the arm brakes along its path at
        the acceleration limit (a controlled stop) and locks until unlocked."""
        with self.lock:
            self._lock_out(reason)
            self.program_running = self.teaching = False
            self.reference.stop(self.limits.acceleration)

    def _lock_out(self, reason: str) -> None:
        self.safety_mode = SafetyMode.PROTECTIVE_STOP
        self.fault = reason
        print(f"emulator: protective stop: {reason}", file=sys.stderr, flush=True)

    def _within_range(self, q: np.ndarray, what: str) -> bool:
        """Whether ``q`` is within the joint range; if not, a protective stop says why."""
        beyond = self.limits.beyond(np.asarray(q, float))
        if beyond:
            names = ", ".join(self.cell.layout.arm_joints[i] for i in beyond)
            self.limit_stop(f"the {what} is beyond the joint limits of {names}")
        return not beyond

    def emergency_stop(self) -> None:
        with self.lock:
            self.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
            self.robot_mode = RobotMode.POWER_OFF
            self._halt()

    def unlock_protective_stop(self) -> bool:
        with self.lock:
            if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
                return False
            self.safety_mode = SafetyMode.NORMAL
            self.fault = None
            return True

    def release_emergency_stop(self) -> None:
        """The person released the button and powered the arm on again."""
        with self.lock:
            if self.safety_mode == SafetyMode.ROBOT_EMERGENCY_STOP:
                self.safety_mode = SafetyMode.NORMAL
                self.robot_mode = RobotMode.RUNNING

    def _halt(self) -> None:
        self.program_running = self.teaching = False
        self.reference.hold(self.cell.arm_q)

    # ------------------------------------------------------------------ scene
    def arrange(self, config: TaskConfig) -> None:
        """Put the task's objects where ``config`` says (what the person does at a reset);
        the arm stays where it is."""
        with self.lock:
            q, qd = self.cell.arm_q, self.cell.data.qvel[self.cell.arm_dof].copy()
            gripper = self.gripper_position
            self._tracker = self.task.start(self.cell, config)
            self.cell.data.qpos[self.cell.arm_qpos] = q
            self.cell.data.qvel[self.cell.arm_dof] = qd
            self.cell.data.ctrl[self.cell.arm_act] = self.reference.q
            if self.cell.gripper_act is not None:
                self.cell.data.ctrl[self.cell.gripper_act] = gripper
            self.cell.finish_reset()

    def ground_truth(self) -> dict:
        """What only the emulator knows: the task's progress and the objects' poses."""
        with self.lock:
            progress = self._tracker.update()
            return {
                "success": bool(progress.success),
                "terms": {k: float(v) for k, v in progress.terms.items()},
                "environment_state": self.cell.environment_vector().tolist(),
            }

    # ------------------------------------------------------------------- tick
    def tick(self) -> None:
        """One servo period: advance the joint reference, step the physics, check safety."""
        with self.lock:
            reference = self.reference
            reference.advance(self.speed_fraction)
            cell = self.cell
            # Velocity feed-forward, as a UR's servo does: the position servo would lag its
            # reference by damping/stiffness x speed; leading the reference by as much
            # lets the arm track it closely at any speed.
            cell.data.ctrl[cell.arm_act] = reference.q + self._lead * reference.qd
            if cell.gripper_act is not None:
                gripper = self.gripper_position
                if self.gripper_output is not None:
                    gripper = float(bool(self.digital_out >> self.gripper_output & 1))
                cell.data.ctrl[cell.gripper_act] = gripper
            mujoco.mj_step(cell.model, cell.data, nstep=self.physics_per_tick)
            mujoco.mj_forward(cell.model, cell.data)
            self.ticks += 1
            if self.safety_mode == SafetyMode.NORMAL:
                self._check_safety()

    def _check_safety(self) -> None:
        """The protective stops a UR's safety system raises: the arm against the table,
        a joint beyond its range or faster than its speed limit."""
        contact = self._table_contact()
        if contact:
            self.protective_stop(contact)
            return
        if not self._within_range(self.reference.q, "arm"):
            return
        speed = np.abs(self.cell.data.qvel[self.cell.arm_dof])
        fastest = int(np.argmax(speed))
        if speed[fastest] > self.limits.speed * SPEED_MARGIN:
            self.limit_stop(
                f"joint {self.cell.layout.arm_joints[fastest]} moved at "
                f"{speed[fastest]:.2f} rad/s, beyond its {self.limits.speed:.2f} rad/s limit"
            )

    def _table_contact(self) -> str:
        """Why the arm must stop for the table ("" when it need not): one of its links
        touches it, or the tool presses on it harder than a UR's force limit."""
        data, model = self.cell.data, self.cell.model
        force = np.zeros(6)
        pressing = 0.0
        for i in range(data.ncon):
            contact = data.contact[i]
            geoms = (contact.geom1, contact.geom2)
            if self._table not in geoms:
                continue
            other = geoms[1] if geoms[0] == self._table else geoms[0]
            body = int(model.geom_bodyid[other])
            if body in self._arm_link_bodies:
                name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
                return f"the arm's {name} link hit the table"
            if body in self._robot_bodies:
                mujoco.mj_contactForce(model, data, i, force)
                pressing += abs(force[0])
        if pressing > PROTECTIVE_FORCE:
            return (
                f"the tool pressed on the table with {pressing:.0f} N, "
                f"over the {PROTECTIVE_FORCE:.0f} N force limit"
            )
        return ""

    # ---------------------------------------------------------------- reading
    def read(self) -> ArmReading:
        with self.lock:
            cell, data = self.cell, self.cell.data
            torque = cell.joint_torques()
            reference = self.reference
            return ArmReading(
                timestamp=self.ticks * self.period,
                q=cell.arm_q,
                qd=data.qvel[cell.arm_dof].copy(),
                qdd=data.qacc[cell.arm_dof].copy(),
                target_q=reference.q.copy(),
                target_qd=reference.qd.copy(),
                target_qdd=reference.qdd.copy(),
                torque=torque,
                current=torque / self.torque_constant,
                tcp_pose=self._tcp_pose(),
                tcp_speed=self._tcp_speed(),
                tcp_force=self._tcp_force(),
                robot_mode=int(self.robot_mode),
                safety_mode=int(self.safety_mode),
                runtime_state=int(
                    RuntimeState.PLAYING if self.program_running else RuntimeState.STOPPED
                ),
                gripper_position=self.gripper_position,
                gripper_opening=cell.gripper_opening,
                digital_out=self.digital_out,
                speed_fraction=self.speed_fraction,
            )

    def _tcp_pose(self) -> np.ndarray:
        """The configured TCP in the robot base frame, as [x, y, z, rx, ry, rz]."""
        return self.tool.pose(self.cell.arm_q)

    def _tcp_speed(self) -> np.ndarray:
        model, data = self.cell.model, self.cell.data
        velocity = np.zeros(6)
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, self._flange, velocity, 0)
        return np.concatenate([velocity[3:], velocity[:3]])

    def _tcp_force(self) -> np.ndarray:
        """Contact wrench on the robot's tool (flange subtree), world-aligned."""
        model, data = self.cell.model, self.cell.data
        tool = self._tool_bodies
        total = np.zeros(6)
        for i in range(data.ncon):
            contact = data.contact[i]
            bodies = (model.geom_bodyid[contact.geom1], model.geom_bodyid[contact.geom2])
            if (bodies[0] in tool) == (bodies[1] in tool):
                continue
            local = np.zeros(6)
            mujoco.mj_contactForce(model, data, i, local)
            frame = contact.frame.reshape(3, 3)
            sign = -1.0 if bodies[0] in tool else 1.0
            total[:3] += sign * frame.T @ local[:3]
        return total
