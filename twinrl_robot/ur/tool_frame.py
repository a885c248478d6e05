"""The controller's TCP: the flange composed with the configured tool offset, in the
robot's base frame, as a UR controller reports and commands it (``actual_TCP_pose``,
servoL). Poses are ``[x, y, z, rx, ry, rz]``: metres and an axis-angle vector (rad).

The driver uses it to turn its guarded joint targets into servoL poses; the emulator to
turn servoL poses back into joint targets (damped least squares on the flange).
"""

from __future__ import annotations

import mujoco
import numpy as np

from twinrl_sim.control import quat_conj, quat_mul, quat_to_rotvec, rotvec_to_quat
from twinrl_sim.layout import MOUNT_BODY

IK_ITERATIONS = 20
IK_DAMPING = 1e-3
IK_TOLERANCE = 1e-7


class ToolFrame:
    """The TCP at ``tcp_offset`` (flange frame) of ``model``'s arm.

    Args:
        model: the cell's model (twin or plant).
        flange_body: the arm's flange body.
        joints: the arm's joint names, in order.
        tcp_offset: the controller's TCP: m, then axis-angle rad, in the flange frame.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        flange_body: str,
        joints: tuple[str, ...],
        tcp_offset: tuple[float, ...],
    ) -> None:
        self.model = model
        self._data = mujoco.MjData(model)
        self._flange = model.body(flange_body).id
        self._base = model.body(MOUNT_BODY).id
        self._qpos = np.array([model.joint(j).qposadr[0] for j in joints])
        self._dof = np.array([model.joint(j).dofadr[0] for j in joints])
        self.set_offset(tcp_offset)

    def set_offset(self, tcp_offset: tuple[float, ...] | np.ndarray) -> None:
        """Configure another TCP (what the controller's ``set_tcp`` does)."""
        self.offset = np.asarray(tcp_offset, float)
        self._offset_quat = rotvec_to_quat(self.offset[3:])

    def pose(self, q: np.ndarray, tool: bool = True) -> np.ndarray:
        """The TCP pose for joint positions ``q`` (the flange's with ``tool=False``)."""
        position, quat = self._pose(np.asarray(q, float), tool)
        return np.concatenate([position, quat_to_rotvec(quat)])

    def solve(self, pose: np.ndarray, q_start: np.ndarray) -> np.ndarray:
        """Joint positions near ``q_start`` that put the TCP at ``pose``."""
        goal_position = np.asarray(pose[:3], float)
        goal_quat = rotvec_to_quat(np.asarray(pose[3:], float))
        q = np.array(q_start, float)
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        for _ in range(IK_ITERATIONS):
            position, quat = self._pose(q)
            error = np.concatenate(
                [goal_position - position, quat_to_rotvec(quat_mul(goal_quat, quat_conj(quat)))]
            )
            if error @ error < IK_TOLERANCE**2:
                break
            mujoco.mj_comPos(self.model, self._data)
            point = self._world_point()
            mujoco.mj_jac(self.model, self._data, jacp, jacr, point, self._flange)
            base = self._base_rotation()
            jac = np.vstack([base.T @ jacp[:, self._dof], base.T @ jacr[:, self._dof]])
            q = q + jac.T @ np.linalg.solve(jac @ jac.T + IK_DAMPING * np.eye(6), error)
        return q

    def _pose(self, q: np.ndarray, tool: bool = True) -> tuple[np.ndarray, np.ndarray]:
        data = self._data
        data.qpos[self._qpos] = q
        mujoco.mj_kinematics(self.model, data)
        base = self._base_rotation()
        world = self._world_point() if tool else data.xpos[self._flange]
        position = base.T @ (world - data.xpos[self._base])
        flange_quat, base_quat = data.xquat[self._flange], data.xquat[self._base]
        if tool:
            flange_quat = quat_mul(flange_quat, self._offset_quat)
        quat = quat_mul(quat_conj(base_quat), flange_quat)
        return position, quat / np.linalg.norm(quat)

    def _world_point(self) -> np.ndarray:
        rotation = self._data.xmat[self._flange].reshape(3, 3)
        return self._data.xpos[self._flange] + rotation @ self.offset[:3]

    def _base_rotation(self) -> np.ndarray:
        return self._data.xmat[self._base].reshape(3, 3)
