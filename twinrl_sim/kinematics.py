"""The twin's forward kinematics of logged joints: TCP poses for logs that lack them, and
the controller's TCP frame mapped onto the twin's."""

from __future__ import annotations

import mujoco
import numpy as np

from twinrl_sim.build import CompiledScene
from twinrl_sim.control import quat_conj, quat_mul
from twinrl_sim.errors import TwinError
from twinrl_sim.layout import MOUNT_BODY


class TcpKinematics:
    """``fk(q) -> (tcp xyz (m), tcp quaternion wxyz)`` in the base frame for one row of
    arm joint positions (rad): fills in the TCP pose of logs that hold only joints."""

    def __init__(self, scene: CompiledScene) -> None:
        self.model = scene.model
        self.data = mujoco.MjData(self.model)
        self._qpos = np.array([self.model.joint(j).qposadr[0] for j in scene.layout.arm_joints])
        self._site = self.model.site(scene.layout.tcp_site).id

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.data.qpos[self._qpos] = np.asarray(q, float)
        mujoco.mj_kinematics(self.model, self.data)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[self._site])
        return self.data.site_xpos[self._site].copy(), quat


class ControllerTcp:
    """Maps a robot controller's TCP poses into the twin's TCP frame.

    A UR reports (and its RTDE recorder logs) the TCP configured on its pendant,
    ``tcp_offset`` from the flange (m, then axis-angle rad, flange frame), in the robot's
    base frame. The twin's TCP is its ``tcp`` site, in the world frame. Both hang off the
    same flange, so each logged pose becomes the twin's: base to world, the configured
    tool back to the flange, the flange to the twin's TCP.
    """

    def __init__(self, scene: CompiledScene, tcp_offset: np.ndarray | list[float]) -> None:
        offset = np.asarray(tcp_offset, float)
        if offset.shape != (6,) or not np.isfinite(offset).all():
            raise TwinError(f"a TCP offset is 6 finite numbers (x y z rx ry rz), got {offset}")
        model = scene.model
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        flange = model.body(scene.layout.flange_body).id
        base = model.body(MOUNT_BODY).id
        site = model.site(scene.layout.tcp_site).id
        self._base = (data.xpos[base].copy(), data.xquat[base].copy())
        flange_rot = data.xmat[flange].reshape(3, 3)
        site_quat = np.zeros(4)
        mujoco.mju_mat2Quat(site_quat, data.site_xmat[site])
        # The twin's TCP in the flange frame, and the configured tool's inverse.
        self._flange_to_site = (
            flange_rot.T @ (data.site_xpos[site] - data.xpos[flange]),
            quat_mul(quat_conj(data.xquat[flange]), site_quat),
        )
        tool_quat = np.zeros(4)
        angle = float(np.linalg.norm(offset[3:]))
        tool_quat[0] = 1.0
        if angle > 1e-12:
            mujoco.mju_axisAngle2Quat(tool_quat, offset[3:] / angle, angle)
        tool_inverse_quat = quat_conj(tool_quat)
        self._tool_to_flange = (-_rotate(tool_inverse_quat, offset[:3]), tool_inverse_quat)

    def __call__(self, positions: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out_pos, out_quat = [], []
        for position, quat in zip(
            np.asarray(positions, float), np.asarray(quats, float), strict=True
        ):
            pose = (position, quat)
            for step in (self._tool_to_flange, self._flange_to_site):
                pose = _compose(pose, step)
            pose = _compose(self._base, pose)
            out_pos.append(pose[0])
            out_quat.append(pose[1])
        return np.array(out_pos), np.array(out_quat)


def _compose(
    first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``second`` (given in ``first``'s frame) in ``first``'s parent frame."""
    quat = quat_mul(first[1], second[1])
    return first[0] + _rotate(first[1], second[0]), quat / np.linalg.norm(quat)


def _rotate(quat: np.ndarray, vector: np.ndarray) -> np.ndarray:
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.asarray(vector, float), np.asarray(quat, float))
    return out
