"""Link frames of the twin's robot for a logged state: what Rerun draws in 3D."""

from __future__ import annotations

import mujoco
import numpy as np

from twinrl_sim.build import CompiledScene
from twinrl_sim.errors import TwinError


class LinkFrames:
    """``frames(state_row) -> {link: (xyz, quat wxyz)}`` by forward kinematics.

    Joint values are read from the ``q.<joint>`` entries of ``observation.state`` (their
    order is given by ``state_names``); the twin's own scene supplies the kinematics.
    """

    def __init__(self, scene: CompiledScene, state_names: list[str]) -> None:
        self.model = scene.model
        self.data = mujoco.MjData(self.model)
        index = {name: i for i, name in enumerate(state_names)}
        joints = [j for j in scene.layout.arm_joints if f"q.{j}" in index]
        if len(joints) != len(scene.layout.arm_joints):
            missing = sorted(set(scene.layout.arm_joints) - set(joints))
            raise TwinError(
                f"the logged state lacks joint positions q.{missing[0]} (and maybe more)"
            )
        self._state_index = np.array([index[f"q.{j}"] for j in joints])
        self._qpos = np.array([self.model.joint(j).qposadr[0] for j in joints])
        self._bodies = {}
        for j in joints:
            body = self.model.jnt_bodyid[self.model.joint(j).id]
            self._bodies[self.model.body(body).name] = body
        self._bodies[scene.layout.flange_body] = self.model.body(scene.layout.flange_body).id

    def __call__(self, state_row: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        self.data.qpos[self._qpos] = np.asarray(state_row, float)[self._state_index]
        mujoco.mj_kinematics(self.model, self.data)
        return {
            name: (self.data.xpos[b].copy(), self.data.xquat[b].copy())
            for name, b in self._bodies.items()
        }


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
