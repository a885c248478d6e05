"""End-effector delta control: the episode contract's 7-D action to joint targets.

An action is ``[dx, dy, dz, rx, ry, rz, gripper]``: a TCP translation (m) and an
axis-angle rotation (rad), both in the robot base frame, plus a gripper command in
[0, 1]. The controller keeps a commanded TCP pose and moves it by each action, clamped
to the workspace box and to ``max_windup`` from the measured TCP. The servo goal is the
commanded pose limited to ``max_lead`` ahead of the measured TCP (so a blocked arm
presses with a bounded force and a lagging arm catches up without losing motion); it is
reached by damped-least-squares differential IK from the last joint target, clamped to
the joint limits and to the joint speed limit over one control period.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_sim.build import CellLayout

ACTION_DIM = 7
MAX_TRANSLATION = 0.05  # m per control step (0.5 m/s at 10 Hz)
MAX_ROTATION = 0.25  # rad per control step
# How fast (rad per control step) the arm's wrist turns without falling behind its
# command, where the arm does not travel far; faster lags more (docs/results/defaults.md).
# Demonstrators turn no faster (the scripted expert also paces its turn by the measured
# yaw): a policy sees only the measured pose, and demos that had commanded a whole turn
# while the arm was a third of the way round taught it to stop turning early.
TRACKED_ROTATION = 0.1


@dataclass(frozen=True)
class IKSettings:
    """Differential-IK tuning. ``damping`` is the DLS lambda (m or rad)."""

    damping: float = 0.02
    iterations: int = 4
    tolerance: float = 1e-5
    max_lead: float = 0.05  # how far (m) the servo target may run ahead of the measured TCP
    max_windup: float = 0.25  # how far (m) the commanded pose may run ahead of it
    joint_margin: float = 0.01  # rad kept from each joint limit
    max_joint_speed: float = np.pi  # rad/s


def action_bounds() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the 7-D action."""
    high = np.array([MAX_TRANSLATION] * 3 + [MAX_ROTATION] * 3 + [1.0], dtype=np.float32)
    low = -high
    low[6] = 0.0
    return low, high


def quat_to_rotvec(quat: np.ndarray) -> np.ndarray:
    """Axis-angle vector (rad) of a unit quaternion (w, x, y, z), shortest rotation."""
    q = np.asarray(quat, float)
    if q[0] < 0:
        q = -q
    vec = np.zeros(3)
    mujoco.mju_quat2Vel(vec, q, 1.0)
    return vec


def rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of an axis-angle vector (rad)."""
    angle = float(np.linalg.norm(rotvec))
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    if angle > 1e-12:
        mujoco.mju_axisAngle2Quat(quat, np.asarray(rotvec, float) / angle, angle)
    return quat


def _limit_distance(point: np.ndarray, anchor: np.ndarray, radius: float) -> np.ndarray:
    """``point`` pulled onto the ball of ``radius`` around ``anchor`` if it lies outside."""
    offset = point - anchor
    norm = float(np.linalg.norm(offset))
    return point if norm <= radius else anchor + offset * (radius / norm)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


class EndEffectorController:
    """Stateful DLS differential-IK controller for one arm.

    ``reset(q)`` sets the commanded pose from joint positions; ``joint_targets(action,
    measured_q)`` returns the next joint targets. It owns a scratch ``MjData`` for
    kinematics, so it never touches the simulation's state.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        layout: CellLayout,
        workspace: tuple[np.ndarray, np.ndarray],
        control_dt: float,
        settings: IKSettings = IKSettings(),
    ) -> None:
        self.model = model
        self.settings = settings
        self.workspace_low, self.workspace_high = (np.asarray(w, float) for w in workspace)
        self._scratch = mujoco.MjData(model)
        self._site = model.site(layout.tcp_site).id
        joint_ids = [model.joint(name).id for name in layout.arm_joints]
        self._qpos_adr = np.array([model.jnt_qposadr[j] for j in joint_ids])
        self._dof_adr = np.array([model.jnt_dofadr[j] for j in joint_ids])
        limited = model.jnt_limited[joint_ids].astype(bool)
        ranges = model.jnt_range[joint_ids].copy()
        ranges[~limited] = [-np.inf, np.inf]
        self.q_low = ranges[:, 0] + settings.joint_margin
        self.q_high = ranges[:, 1] - settings.joint_margin
        self.max_joint_step = settings.max_joint_speed * control_dt
        self.q_target = np.zeros(len(joint_ids))
        self.pos_cmd = np.zeros(3)
        self.quat_cmd = np.array([1.0, 0.0, 0.0, 0.0])

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and quaternion (w, x, y, z) in the base frame for arm joints ``q``."""
        data = self._scratch
        data.qpos[self._qpos_adr] = q
        mujoco.mj_kinematics(self.model, data)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, data.site_xmat[self._site])
        return data.site_xpos[self._site].copy(), quat

    def reset(self, q: np.ndarray) -> None:
        """Start from joint positions ``q``: the command becomes the pose they give."""
        self.q_target = np.array(q, float)
        self.pos_cmd, self.quat_cmd = self.forward(self.q_target)

    def joint_targets(self, action: np.ndarray, measured_q: np.ndarray) -> np.ndarray:
        """Apply the arm part of ``action`` and return the new joint targets (rad)."""
        action = np.asarray(action, float)
        delta = np.clip(action[:3], -MAX_TRANSLATION, MAX_TRANSLATION)
        rot = np.asarray(action[3:6], float)
        angle = np.linalg.norm(rot)
        if angle > MAX_ROTATION:
            rot = rot * (MAX_ROTATION / angle)
        measured_pos, _ = self.forward(np.asarray(measured_q, float))
        pos = np.clip(self.pos_cmd + delta, self.workspace_low, self.workspace_high)
        pos = _limit_distance(pos, measured_pos, self.settings.max_windup)
        quat = quat_mul(rotvec_to_quat(rot), self.quat_cmd)
        quat /= np.linalg.norm(quat)
        servo_goal = _limit_distance(pos, measured_pos, self.settings.max_lead)
        self.q_target = self.solve(servo_goal, quat, self.q_target)
        self.pos_cmd, self.quat_cmd = pos, quat
        return self.q_target.copy()

    def solve(self, pos: np.ndarray, quat: np.ndarray, q_start: np.ndarray) -> np.ndarray:
        """DLS IK toward (pos, quat) from ``q_start``, limited to one control period's motion."""
        settings = self.settings
        data = self._scratch
        q = np.array(q_start, float)
        jacp = np.zeros((3, self.model.nv))
        jacr = np.zeros((3, self.model.nv))
        lam2 = settings.damping**2
        for _ in range(settings.iterations):
            cur_pos, cur_quat = self.forward(q)
            err = np.concatenate(
                [pos - cur_pos, quat_to_rotvec(quat_mul(quat, quat_conj(cur_quat)))]
            )
            if np.linalg.norm(err) < settings.tolerance:
                break
            mujoco.mj_comPos(self.model, data)
            mujoco.mj_jacSite(self.model, data, jacp, jacr, self._site)
            jac = np.vstack([jacp[:, self._dof_adr], jacr[:, self._dof_adr]])
            dq = jac.T @ np.linalg.solve(jac @ jac.T + lam2 * np.eye(6), err)
            q = np.clip(q + dq, self.q_low, self.q_high)
        step = np.clip(q - q_start, -self.max_joint_step, self.max_joint_step)
        return np.clip(q_start + step, self.q_low, self.q_high)

    def solve_pose(
        self, pos: np.ndarray, quat: np.ndarray, q_start: np.ndarray, iterations: int = 200
    ) -> np.ndarray:
        """Full IK (no speed limit) for setting up poses, e.g. a home configuration."""
        q = np.array(q_start, float)
        for _ in range(iterations):
            q_next = self.solve(pos, quat, q)
            if np.allclose(q_next, q, atol=1e-9):
                break
            q = q_next
        return q
