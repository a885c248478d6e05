"""The twin's cell as Rerun geometry, posed by logged episodes: what ``twinrl view`` draws.

:class:`TwinCell` turns every visible geom of the twin's model (the arm's links, the
gripper and its fingers, the table, the objects) into Rerun shapes in its body's frame
(boxes, capsules, cylinders, spheres, planes and meshes), logged once as static
geometry; per logged step it says where each moving body is, by the twin's forward
kinematics of the logged joints and gripper opening and the logged object poses, so a
long episode adds a transform per body and step, never geometry again. Poses are in
the world frame of the twin, which is the arm's base frame the episodes log poses in.
It also says what the robot touches at a logged step (:meth:`TwinCell.contacts`): the
twin's collision detection run on the logged configuration, since no cell measures
contacts. A live view asks step by step; a saved one asks for a whole episode at once
(:meth:`TwinCell.steps`), which only MuJoCo's calls run through step by step. It
satisfies :class:`twinrl_data.view.CellModel`.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import mujoco
import numpy as np
import rerun as rr

from twinrl_data.contact_view import Contact
from twinrl_data.mcap_log import pose_groups
from twinrl_data.view import CameraMount, CellSteps, Pose
from twinrl_sim.build import CompiledScene
from twinrl_sim.errors import TwinError
from twinrl_sim.robots.gripper import joint_from_opening

PLANE_EXTENT = 1.5  # m: half-size drawn for an infinite plane (the floor)
PLANE_THICKNESS = 0.001  # m
HIDDEN_GROUPS = 3  # geoms in group 3 and above are collision-only by MuJoCo convention
# m: surfaces this close count as touching; a logged pose's millimetre of noise would
# otherwise make a finger on an object flicker in and out of contact
CONTACT_GAP = 0.002


def _xyzw(wxyz: np.ndarray) -> rr.Quaternion:
    return rr.Quaternion(xyzw=[wxyz[1], wxyz[2], wxyz[3], wxyz[0]])


def _rotate(wxyz: np.ndarray, vector: np.ndarray) -> np.ndarray:
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.asarray(vector, float), np.asarray(wxyz, float))
    return out


class TwinCell:
    """The twin of ``scene`` posed by episodes whose ``observation.state`` entries are
    named ``state_names`` and ``observation.environment_state`` ones
    ``environment_names`` (empty: the objects are not drawn, since nothing says where
    they are)."""

    def __init__(
        self,
        scene: CompiledScene,
        state_names: Sequence[str],
        environment_names: Sequence[str] = (),
    ) -> None:
        self.model = model = scene.model
        self.data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, self.data)
        index = {name: i for i, name in enumerate(state_names)}
        missing = [j for j in scene.layout.arm_joints if f"q.{j}" not in index]
        if missing:
            raise TwinError(
                f"the logged state lacks joint positions q.{missing[0]} (and maybe more)"
            )
        # Where each arm joint is in a state row, and in the model's qpos.
        self._arm_columns = np.array([index[f"q.{j}"] for j in scene.layout.arm_joints])
        self._arm_addresses = np.array([model.joint(j).qposadr[0] for j in scene.layout.arm_joints])
        self._opening = index.get("gripper.opening")
        fingers = np.array(
            [] if self._opening is None else self._finger_joints(scene), float
        ).reshape(-1, 3)
        self._finger_addresses = fingers[:, 0].astype(int)
        self._finger_offsets, self._finger_gains = fingers[:, 1], fingers[:, 2]
        groups = pose_groups(list(environment_names))
        self._objects = [
            (body, groups[model.body(body).name])
            for body in range(1, model.nbody)
            if model.body(body).name in groups
        ]
        posed = {body for body, _ in self._objects}
        roots = model.body_rootid
        # An object whose pose is not logged is not drawn: the twin cannot know where it is.
        self._hidden = {
            b for b in range(1, model.nbody) if roots[b] not in posed and self._is_object(b)
        }
        self._moving = [
            b
            for b in range(1, model.nbody)
            if b not in self._hidden and (model.body_weldid[b] != 0 or model.body_mocapid[b] >= 0)
        ]
        # The robot's moving bodies (links, gripper, fingers): the ones whose contacts
        # are drawn (its base's seat on the table is always there and says nothing).
        arm_root = model.body_rootid[model.jnt_bodyid[model.joint(scene.layout.arm_joints[0]).id]]
        self._is_robot = (model.body_rootid == arm_root) & (model.body_weldid != 0)
        self._is_hidden = np.isin(np.arange(model.nbody), list(self._hidden))
        self._body_names = [model.body(b).name for b in range(model.nbody)]
        self._touch_model = self._touching_model()
        self._touch_data = mujoco.MjData(self._touch_model)
        self._last_posed: tuple[bytes, bytes | None] | None = None

    def _touching_model(self) -> mujoco.MjModel:
        """A copy of the model whose collision detection answers only what the view asks:
        surfaces within CONTACT_GAP count, and only pairs of a robot's moving body and
        a posed body that is not the robot's are checked (a geom that collides with
        nothing stays so). The drawn model is left as is; the copy's data poses the cell
        at each step, for its poses and its contacts."""
        model = self.model
        touch = copy.copy(model)
        touch.geom_margin[:] = np.maximum(model.geom_margin, CONTACT_GAP)
        colliding = (model.geom_contype | model.geom_conaffinity) != 0
        robot = self._is_robot[model.geom_bodyid]
        posed = ~self._is_hidden[model.geom_bodyid]
        touch.geom_contype[:] = colliding & robot
        touch.geom_conaffinity[:] = colliding & ~robot & posed
        return touch

    def _is_object(self, body: int) -> bool:
        """A body that is neither welded to the world nor part of the arm: a free object."""
        model = self.model
        root = model.body_rootid[body]
        if model.body_mocapid[root] >= 0:
            return True
        return bool(
            root != 0
            and model.body_jntnum[root] > 0
            and model.jnt_type[model.body_jntadr[root]] == mujoco.mjtJoint.mjJNT_FREE
        )

    def _finger_joints(self, scene: CompiledScene) -> list[tuple[int, float, float]]:
        """(qpos address, offset, gain) of the driven finger joint and of every joint an
        equality constraint couples to it (the mirrored finger)."""
        joint = scene.layout.gripper_joint
        if joint is None:
            return []
        model = self.model
        driven = model.joint(joint).id
        out = [(model.jnt_qposadr[driven], 0.0, 1.0)]
        for e in range(model.neq):
            if model.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and model.eq_obj2id[e] == driven:
                coupled = model.eq_obj1id[e]
                out.append((model.jnt_qposadr[coupled], model.eq_data[e][0], model.eq_data[e][1]))
        return out

    # ------------------------------------------------------------------ geometry
    def geometry(self, opacity: int = 255) -> dict[str, list[object]]:
        """Every drawn body's shapes in its own frame, by body name (Rerun archetypes),
        at ``opacity`` (0-255; a ghost drawn over another cell is translucent)."""
        model = self.model
        out: dict[str, list[object]] = {}
        for geom in range(model.ngeom):
            body = int(model.geom_bodyid[geom])
            rgba = model.geom_rgba[geom]
            if body in self._hidden or model.geom_group[geom] >= HIDDEN_GROUPS or rgba[3] == 0:
                continue
            color = (np.clip(rgba, 0, 1) * 255).astype(np.uint8)
            color[3] = min(int(color[3]), opacity)
            shape = self._shape(geom, color)
            if shape is not None:
                out.setdefault(model.body(body).name, []).append(shape)
        return out

    def _shape(self, geom: int, color: np.ndarray) -> object | None:
        model = self.model
        kind, size = model.geom_type[geom], model.geom_size[geom]
        center, quat = model.geom_pos[geom], model.geom_quat[geom]
        types = mujoco.mjtGeom
        if kind == types.mjGEOM_BOX:
            return rr.Boxes3D(half_sizes=[size], centers=[center], quaternions=[_xyzw(quat)],
                              colors=[color], fill_mode="solid")  # fmt: skip
        if kind == types.mjGEOM_PLANE:
            half = [size[0] or PLANE_EXTENT, size[1] or PLANE_EXTENT, PLANE_THICKNESS]
            return rr.Boxes3D(half_sizes=[half], centers=[center], quaternions=[_xyzw(quat)],
                              colors=[color], fill_mode="solid")  # fmt: skip
        if kind == types.mjGEOM_SPHERE:
            return rr.Ellipsoids3D(half_sizes=[[size[0]] * 3], centers=[center],
                                   colors=[color], fill_mode="solid")  # fmt: skip
        if kind == types.mjGEOM_ELLIPSOID:
            return rr.Ellipsoids3D(half_sizes=[size], centers=[center], quaternions=[_xyzw(quat)],
                                   colors=[color], fill_mode="solid")  # fmt: skip
        if kind == types.mjGEOM_CYLINDER:
            return rr.Cylinders3D(lengths=[2 * size[1]], radii=[size[0]], centers=[center],
                                  quaternions=[_xyzw(quat)], colors=[color],
                                  fill_mode="solid")  # fmt: skip
        if kind == types.mjGEOM_CAPSULE:
            # Rerun's capsule runs from its translation along +z; MuJoCo's is centred.
            start = center - _rotate(quat, [0.0, 0.0, size[1]])
            return rr.Capsules3D(lengths=[2 * size[1]], radii=[size[0]], translations=[start],
                                 quaternions=[_xyzw(quat)], colors=[color])  # fmt: skip
        if kind == types.mjGEOM_MESH:
            mesh = model.geom_dataid[geom]
            first, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            faces = model.mesh_face[model.mesh_faceadr[mesh] : model.mesh_faceadr[mesh]
                                    + model.mesh_facenum[mesh]]  # fmt: skip
            vertices = np.array([_rotate(quat, v) for v in model.mesh_vert[first : first + count]])
            return rr.Mesh3D(vertex_positions=vertices + center, triangle_indices=faces,
                             albedo_factor=color)  # fmt: skip
        return None  # heightfields and signed-distance shapes are not drawn

    def cameras(self) -> dict[str, CameraMount]:
        """The model's cameras on their bodies (a camera on a hidden object is left out)."""
        model = self.model
        return {
            model.camera(c).name: CameraMount(
                body=model.body(int(model.cam_bodyid[c])).name,
                position=model.cam_pos[c].copy(),
                quaternion=model.cam_quat[c].copy(),
                fov_y_deg=float(model.cam_fovy[c]),
            )
            for c in range(model.ncam)
            if int(model.cam_bodyid[c]) not in self._hidden
        }

    # ------------------------------------------------------------------ poses
    def fixed_poses(self) -> dict[str, Pose]:
        """Where the drawn bodies that never move are (the table, the arm's base)."""
        moving = set(self._moving)
        return {
            self.model.body(b).name: (self.data.xpos[b].copy(), self.data.xquat[b].copy())
            for b in range(1, self.model.nbody)
            if b not in moving and b not in self._hidden
        }

    def __call__(self, state: np.ndarray, environment: np.ndarray | None = None) -> dict[str, Pose]:
        """Where each moving body is at one logged step (its state row and, when the
        episode logs them, its object poses)."""
        data = self._posed(state, environment)
        return {self._body_names[b]: (data.xpos[b].copy(), data.xquat[b].copy())
                for b in self._moving}  # fmt: skip

    def contacts(self, state: np.ndarray, environment: np.ndarray | None = None) -> list[Contact]:
        """What the robot's moving bodies touch at one logged step, as the twin's
        collision geometry sees the logged configuration: each contact's point (world
        frame) and the two bodies (the robot's first), nearest first for each pair.
        Surfaces within :data:`CONTACT_GAP` count; an object whose pose is not logged
        is not there."""
        data = self._posed(state, environment)
        mujoco.mj_collision(self._touch_model, data)
        return self._touching(data)

    def steps(self, states: np.ndarray, environments: np.ndarray | None = None) -> CellSteps:
        """The moving bodies' poses and the robot's contacts at every logged step (its
        state rows and object-pose rows), as :meth:`__call__` and :meth:`contacts` say
        them step by step. The configurations are built as arrays, so only MuJoCo's
        kinematics and collision detection run once a step. A step whose object pose
        is not finite keeps the object's last logged pose (its place in the model
        before the first)."""
        model, data = self._touch_model, self._touch_data
        qpos, mocap_pos, mocap_quat = self._configurations(
            states, environments, mujoco.MjData(model)
        )
        positions = np.empty((len(states), model.nbody, 3))  # every body: whole copies
        quats = np.empty((len(states), model.nbody, 4))  # are cheaper than picking
        contacts = []
        for t in range(len(states)):
            data.qpos[:] = qpos[t]
            if model.nmocap:
                data.mocap_pos[:], data.mocap_quat[:] = mocap_pos[t], mocap_quat[t]
            mujoco.mj_kinematics(model, data)
            positions[t], quats[t] = data.xpos, data.xquat
            mujoco.mj_collision(model, data)
            contacts.append(self._touching(data) if data.ncon else [])
        self._last_posed = None
        poses = {self._body_names[b]: (positions[:, b], quats[:, b]) for b in self._moving}
        return CellSteps(poses, contacts)

    def _touching(self, data: mujoco.MjData) -> list[Contact]:
        """The robot's contacts that collision detection left in ``data``, one per pair
        of bodies (the nearest)."""
        count, contacts = data.ncon, data.contact
        dist, pos = contacts.dist[:count], contacts.pos[:count]  # each field read once
        bodies = self._touch_model.geom_bodyid[contacts.geom[:count]]
        robot_first = self._is_robot[bodies[:, 0]]
        robot = np.where(robot_first, bodies[:, 0], bodies[:, 1])
        other = np.where(robot_first, bodies[:, 1], bodies[:, 0])
        keep = (
            self._is_robot[robot]
            & ~self._is_robot[other]
            & ~self._is_hidden[other]
            & (dist <= CONTACT_GAP)
        )
        found: dict[tuple[int, int], int] = {}
        for i in np.flatnonzero(keep):
            pair = (int(robot[i]), int(other[i]))
            if pair not in found or dist[i] < dist[found[pair]]:
                found[pair] = i
        return [
            Contact(pos[i].copy(), self._body_names[r], self._body_names[o], float(dist[i]))
            for (r, o), i in found.items()
        ]

    def _posed(self, state: np.ndarray, environment: np.ndarray | None) -> mujoco.MjData:
        """The cell posed at one step, its kinematics computed; asked again for the same
        step (its poses, then its contacts), the same. An object pose that is not
        finite keeps the object where the step before put it."""
        key = (state.tobytes(), None if environment is None else environment.tobytes())
        if key != self._last_posed:
            data = self._touch_data
            qpos, mocap_pos, mocap_quat = self._configurations(
                state[None], None if environment is None else environment[None], data
            )
            data.qpos[:] = qpos[0]
            data.mocap_pos[:], data.mocap_quat[:] = mocap_pos[0], mocap_quat[0]
            mujoco.mj_kinematics(self._touch_model, data)
            self._last_posed = key
        return self._touch_data

    def _configurations(
        self, states: np.ndarray, environments: np.ndarray | None, before: mujoco.MjData
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model's joint positions (T, nq), mocap positions (T, nmocap, 3) and
        quaternions (T, nmocap, 4) at each step of ``states`` (and ``environments``): the
        arm and the fingers where the state rows say, the logged objects where their
        rows say, and everything else, or an object before its first finite pose, as
        in ``before``."""
        model, steps = self.model, len(states)
        qpos = np.repeat(before.qpos[None], steps, axis=0)
        mocap_pos = np.repeat(before.mocap_pos[None], steps, axis=0)
        mocap_quat = np.repeat(before.mocap_quat[None], steps, axis=0)
        qpos[:, self._arm_addresses] = states[:, self._arm_columns]
        if self._opening is not None:
            finger = joint_from_opening(states[:, self._opening])
            qpos[:, self._finger_addresses] = (
                self._finger_offsets + self._finger_gains * finger[:, None]
            )
        if environments is None:
            return qpos, mocap_pos, mocap_quat
        for body, columns in self._objects:
            pose = environments[:, columns]
            latest = np.where(np.all(np.isfinite(pose[:, :3]), axis=1), np.arange(steps), -1)
            latest = np.maximum.accumulate(latest)
            logged = latest >= 0
            if model.body_mocapid[body] >= 0:
                mocap = model.body_mocapid[body]
                mocap_pos[logged, mocap] = pose[latest[logged], :3]
                mocap_quat[logged, mocap] = pose[latest[logged], 3:]
            else:
                address = model.jnt_qposadr[model.body_jntadr[body]]
                qpos[logged, address : address + 7] = pose[latest[logged]]
        return qpos, mocap_pos, mocap_quat
