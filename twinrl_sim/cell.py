"""The runtime of one simulated cell: model, data, controller and cameras.

A :class:`Cell` is what both the twin envs and the plant step. It knows how to put the
arm and the objects into a state, how to turn a 7-D action into joint targets and
physics steps (``control_hz`` control, ``timestep`` physics), and how to read the
episode contract's observation vectors and camera images.

State vector layout (``observation.state``, see :data:`STATE_NAMES`)::

    q[6] (rad) | qd[6] (rad/s) | tcp xyz[3] (m) | tcp quat wxyz[4] | gripper opening[1] (m)

Environment vector (``observation.environment_state``): for each object of the scene,
in spec order, its position xyz and quaternion wxyz in the base frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_data.lerobot_io import ACTION_NAMES
from twinrl_data.schema import ACTION, ENVIRONMENT_STATE, JOINT_TARGET, STATE
from twinrl_sim.build import CompiledScene
from twinrl_sim.control import EndEffectorController
from twinrl_sim.effects import torque_offset
from twinrl_sim.robots.gripper import joint_from_opening, opening_from_joint
from twinrl_sim.servo import servo_lead, tracking_setpoints


def state_names(arm_joints: tuple[str, ...]) -> list[str]:
    """Names of the entries of ``observation.state`` for an arm with these joints."""
    return (
        [f"q.{j}" for j in arm_joints]
        + [f"qd.{j}" for j in arm_joints]
        + ["tcp.x", "tcp.y", "tcp.z", "tcp.qw", "tcp.qx", "tcp.qy", "tcp.qz", "gripper.opening"]
    )


def environment_names(objects: tuple[str, ...]) -> list[str]:
    """Names of the entries of ``observation.environment_state``."""
    return [f"{o}.{c}" for o in objects for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]


@dataclass(frozen=True)
class StepSignals:
    """What one control step leaves behind, for logs and replay."""

    joint_target: np.ndarray  # rad, (n_arm,)
    gripper_command: float


class Cell:
    """One simulated cell (a twin world or the plant's hidden world)."""

    def __init__(self, scene: CompiledScene) -> None:
        self.scene = scene
        self.model = scene.model
        self.layout = scene.layout
        self.data = mujoco.MjData(self.model)
        self.substeps = scene.spec.physics.substeps
        self.control_dt = 1.0 / scene.spec.physics.control_hz
        model, layout = self.model, self.layout
        self.arm_qpos = np.array([model.joint(j).qposadr[0] for j in layout.arm_joints])
        self.arm_dof = np.array([model.joint(j).dofadr[0] for j in layout.arm_joints])
        self._torque_offset = torque_offset(model, len(self.arm_dof))
        self.arm_act = np.array([model.actuator(a).id for a in layout.arm_actuators])
        self.servo_lead = servo_lead(model)  # None: the servos hold each target
        self._previous_target = np.array(layout.home_qpos, float)
        self.gripper_act = (
            model.actuator(layout.gripper_actuator).id if layout.gripper_actuator else None
        )
        self.gripper_qpos = (
            model.joint(layout.gripper_joint).qposadr[0] if layout.gripper_joint else None
        )
        self.objects = tuple(o.name for o in scene.spec.objects)
        self._object_body = {o: model.body(o).id for o in self.objects}
        self._free_qpos = {o: model.joint(f"{o}_free").qposadr[0] for o in layout.manipulated}
        self._mocap = {o: model.body(o).mocapid[0] for o in layout.placed}
        self.tcp_site = model.site(layout.tcp_site).id
        ws = scene.spec.workspace
        self.controller = EndEffectorController(
            model, layout, (np.array(ws.low), np.array(ws.high)), self.control_dt
        )
        self.state_names = state_names(layout.arm_joints)
        self.environment_names = environment_names(self.objects)
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self.decorations: list[Callable[[mujoco.MjvScene], None]] = []
        """Callbacks that add visual-only geoms (e.g. task marks) to every rendered frame."""

    # ----------------------------------------------------------------- state
    @property
    def table_top(self) -> float:
        """World height (m) of the table top in this model (effects included)."""
        geom = self.model.geom(self.layout.table_geom)
        body = self.model.body(self.layout.table_body)
        return float(body.pos[2] + geom.pos[2] + geom.size[2])

    def reset_robot(self, qpos: np.ndarray | None = None, gripper: float = 0.0) -> None:
        """Reset physics, put the arm at ``qpos`` (default: home), at rest, gripper open.

        Also drops the previous episode's render decorations."""
        mujoco.mj_resetData(self.model, self.data)
        self.decorations.clear()
        q = np.asarray(self.layout.home_qpos if qpos is None else qpos, float)
        self.data.qpos[self.arm_qpos] = q
        self.data.ctrl[self.arm_act] = q
        self._previous_target = q.copy()
        if self.gripper_act is not None:
            self.data.ctrl[self.gripper_act] = gripper
        self.controller.reset(q)

    def hold(self) -> None:
        """Re-anchor the end-effector command at the measured arm pose (the arm stops
        where it is), as a teleop takeover does: the operator's deltas then start from
        what they see, not from wherever the previous commands had wound up."""
        self.controller.reset(self.arm_q)

    def place_object(self, name: str, pos: np.ndarray, quat: np.ndarray) -> None:
        """Put object ``name`` at ``pos`` (world, m) with orientation ``quat`` (wxyz)."""
        if name in self._free_qpos:
            adr = self._free_qpos[name]
            self.data.qpos[adr : adr + 3] = pos
            self.data.qpos[adr + 3 : adr + 7] = quat
        else:
            self.data.mocap_pos[self._mocap[name]] = pos
            self.data.mocap_quat[self._mocap[name]] = quat

    def pose(
        self, arm_q: np.ndarray, opening: float, objects: dict[str, tuple[np.ndarray, np.ndarray]]
    ) -> None:
        """Put the arm at ``arm_q``, the fingers ``opening`` m apart and each of
        ``objects`` at its (position, quaternion wxyz), and update the kinematics without
        stepping the physics: the twin posed as a log or an estimate says (a task's
        progress can then be judged on it)."""
        self.data.qpos[self.arm_qpos] = arm_q
        if self.gripper_qpos is not None:
            self.data.qpos[self.gripper_qpos] = joint_from_opening(opening)
        for name, (pos, quat) in objects.items():
            self.place_object(name, pos, quat)
        mujoco.mj_kinematics(self.model, self.data)

    def finish_reset(self) -> None:
        """Recompute derived quantities and initialise actuator history after placing."""
        if self.model.nhistory:
            # A delayed servo must see the held targets as its past, not zeros.
            for act in np.flatnonzero(self.model.actuator_history[:, 0] > 0):
                samples = int(self.model.actuator_history[act, 0])
                values = np.full(samples, self.data.ctrl[act])
                mujoco.mj_initCtrlHistory(self.model, self.data, int(act), None, values)
        mujoco.mj_forward(self.model, self.data)

    def get_state(self) -> np.ndarray:
        """The full physics state (mjSTATE_FULLPHYSICS), enough to restore the cell."""
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, self.data, state, spec)
        return state

    def set_state(self, state: np.ndarray) -> None:
        mujoco.mj_setState(self.model, self.data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(self.model, self.data)
        self._previous_target = self.arm_q  # tracking servos start from where the arm is

    # --------------------------------------------------------------- control
    def step(self, action: np.ndarray) -> StepSignals:
        """One control step: action -> joint targets -> ``substeps`` physics steps."""
        measured = self.data.qpos[self.arm_qpos]
        targets = self.controller.joint_targets(action, measured)
        gripper = float(np.clip(action[6], 0.0, 1.0))
        self.send(targets, gripper)
        return StepSignals(joint_target=targets, gripper_command=gripper)

    def send(self, joint_target: np.ndarray, gripper: float) -> None:
        """Send ``joint_target`` (rad) and ``gripper`` for one control period: the arm's
        servos hold the target or track it from the previous one (:mod:`twinrl_sim.servo`)."""
        target = np.asarray(joint_target, float)
        if self.gripper_act is not None:
            self.data.ctrl[self.gripper_act] = gripper
        if self.servo_lead is None:
            self.data.ctrl[self.arm_act] = target
            mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        else:
            setpoints = tracking_setpoints(
                self._previous_target[None],
                target[None, None],
                self.substeps,
                self.control_dt,
                self.servo_lead,
            )[0]
            for setpoint in setpoints:
                self.data.ctrl[self.arm_act] = setpoint
                mujoco.mj_step(self.model, self.data)
        self._previous_target = target.copy()
        # mj_step leaves derived quantities one substep stale; observations read them.
        mujoco.mj_forward(self.model, self.data)

    # ----------------------------------------------------------- observation
    @property
    def arm_q(self) -> np.ndarray:
        return self.data.qpos[self.arm_qpos].copy()

    @property
    def gripper_opening(self) -> float:
        if self.gripper_qpos is None:
            return 0.0
        return opening_from_joint(float(self.data.qpos[self.gripper_qpos]))

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Measured TCP position (m) and quaternion (wxyz), base frame."""
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[self.tcp_site])
        return self.data.site_xpos[self.tcp_site].copy(), quat

    def object_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        body = self._object_body[name]
        return self.data.xpos[body].copy(), self.data.xquat[body].copy()

    def joint_torques(self) -> np.ndarray:
        """Torque (N m) the arm's servos apply at each joint (with servos that feed the
        model forward, what a UR reports as ``target_moment``), plus any logged offset."""
        return self.data.qfrc_actuator[self.arm_dof] + self._torque_offset

    def state_vector(self) -> np.ndarray:
        pos, quat = self.tcp_pose()
        return np.concatenate(
            [
                self.data.qpos[self.arm_qpos],
                self.data.qvel[self.arm_dof],
                pos,
                quat,
                [self.gripper_opening],
            ]
        ).astype(np.float32)

    def environment_vector(self) -> np.ndarray:
        parts = []
        for name in self.objects:
            pos, quat = self.object_pose(name)
            parts.extend([pos, quat])
        return np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)

    def contract_names(self) -> dict[str, list[str]]:
        """Names of the entries of every vector field an episode of this cell logs."""
        return {
            STATE: self.state_names,
            ENVIRONMENT_STATE: self.environment_names,
            ACTION: list(ACTION_NAMES),
            JOINT_TARGET: [f"target.{j}" for j in self.layout.arm_joints],
        }

    def render(
        self, camera: str, *, width: int | None = None, height: int | None = None
    ) -> np.ndarray:
        """RGB image (uint8, H x W x 3) from ``camera`` at its spec resolution by default."""
        cam = self.model.camera(camera)
        w = width or int(self.model.cam_resolution[cam.id][0])
        h = height or int(self.model.cam_resolution[cam.id][1])
        renderer = self._renderers.get((w, h))
        if renderer is None:
            renderer = mujoco.Renderer(self.model, height=h, width=w)
            self._renderers[(w, h)] = renderer
        renderer.update_scene(self.data, camera=cam.id)
        for decorate in self.decorations:
            decorate(renderer.scene)
        return renderer.render().copy()

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
