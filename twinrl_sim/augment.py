"""Demo-based augmentation: re-target one recorded demonstration to new configurations.

The demo's commanded TCP path (its start pose integrated with its actions) is split at
two keyframes: the grasp (the gripper closes) and the hand-over to the target (the
gripper opens, or for a tool such as the eraser, first reaches its working height).
Within ``NEAR`` of the grasp the path moves exactly with the object, within ``NEAR`` of
the hand-over (and after it) exactly with the target, and in between it blends from
one frame to the other. Translations follow the planar rigid
motion of the object (an affine map), rotations are slerped toward the same yaw change,
so that at the keyframes the TCP keeps exactly its pose relative to the object and the
target (up to the grasp's symmetry: the gripper's half turn, which the targets here
share). Of the equivalent turns at the object the wrist takes the one that keeps the
grasp as near the task's nominal grasp yaw as the demo's was, as the planner and the
experts grasp, so that re-targeted demos of neighbouring configurations turn the same
way. Gripper commands and timing are kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twinrl_data.schema import ACTION, STATE, Episode
from twinrl_sim.control import quat_conj, quat_mul, quat_to_rotvec, rotvec_to_quat
from twinrl_sim.errors import TwinError
from twinrl_sim.planar import wrap_angle, yaw_of
from twinrl_sim.tasks.base import TaskConfig
from twinrl_sim.tasks.expert import GRIPPER_CLOSED, grasp_yaw

NEAR = 0.10  # m: within this of a keyframe the path follows the object/target exactly


@dataclass(frozen=True)
class PlanarMotion:
    """Rotation about the vertical by ``yaw`` about ``pivot``, then a shift by ``shift``;
    the tool turns by ``tool_turn`` (an equivalent of ``yaw`` under the grasp's symmetry)."""

    pivot: np.ndarray
    yaw: float
    shift: np.ndarray
    tool_turn: float

    @classmethod
    def between(
        cls,
        source: tuple[float, float, float],
        target: tuple[float, float, float],
        tool_turn: float | None = None,
    ) -> PlanarMotion:
        """The motion taking table pose ``source`` (x, y, yaw) to ``target``; the tool
        turns by ``tool_turn`` (default: the half-turn equivalent of the yaw change
        within +-90 deg, the parallel gripper being symmetric under a half turn)."""
        pivot = np.array([source[0], source[1], 0.0])
        shift = np.array([target[0] - source[0], target[1] - source[1], 0.0])
        yaw = target[2] - source[2]
        if tool_turn is None:
            tool_turn = wrap_angle(yaw, math.pi)
        return cls(pivot=pivot, yaw=yaw, shift=shift, tool_turn=tool_turn)

    def apply(self, point: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        offset = point - self.pivot
        turned = np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
        return self.pivot + turned + self.shift

    @property
    def tool_quat(self) -> np.ndarray:
        """The tool's share of the motion: a turn by ``tool_turn`` about the vertical."""
        return rotvec_to_quat(np.array([0.0, 0.0, self.tool_turn]))


def commanded_path(episode: Episode) -> tuple[np.ndarray, np.ndarray]:
    """TCP positions (T + 1, 3) and quaternions (T + 1, 4) the demo commanded."""
    names = episode.meta.names.get(STATE, [])
    try:
        index = [names.index(f"tcp.{c}") for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
    except ValueError:
        raise TwinError(
            "the demo's observation.state has no tcp.x ... tcp.qz entries to re-target"
        ) from None
    start = episode.data[STATE][0][index]
    positions = [start[:3].astype(float)]
    quats = [start[3:].astype(float) / np.linalg.norm(start[3:])]
    for action in episode.data[ACTION]:
        positions.append(positions[-1] + action[:3])
        quat = quat_mul(rotvec_to_quat(action[3:6]), quats[-1])
        quats.append(quat / np.linalg.norm(quat))
    return np.array(positions), np.array(quats)


def keyframes(episode: Episode, releases_object: bool) -> tuple[int, int]:
    """Steps of the grasp and of the hand-over to the target (see the module docstring)."""
    gripper = episode.data[ACTION][:, 6]
    closed = np.flatnonzero(gripper >= GRIPPER_CLOSED)
    if len(closed) == 0:
        raise TwinError("the demo never closes the gripper: nothing to re-target")
    grasp = int(closed[0])
    if releases_object:
        opened = np.flatnonzero((gripper < GRIPPER_CLOSED) & (np.arange(len(gripper)) > grasp))
        # A demo that ended on success while still holding (an insertion) hands over last.
        return grasp, int(opened[0]) if len(opened) else len(gripper)
    positions, _ = commanded_path(episode)
    after = positions[grasp + 5 :, 2]  # working height: the lowest point once lifted
    working = int(np.flatnonzero(after <= after.min() + 0.01)[0]) + grasp + 5
    return grasp, working


def retarget(
    episode: Episode,
    source: TaskConfig,
    target: TaskConfig,
    *,
    releases_object: bool = True,
    grasp_period: float = math.pi,
    grasp_yaw_offset: float = 0.0,
    extend_steps: int = 4,
) -> np.ndarray:
    """Actions (T + extend_steps, 7) that replay ``episode``'s motion for ``target``.

    ``grasp_period`` and ``grasp_yaw_offset`` are the task's (``Task.grasp_period``):
    the wrist turns from the source's nominal grasp yaw to the target's, each the
    equivalent nearest the demo's starting tool yaw.

    A recorded episode stops at the first success signal, i.e. at the success threshold
    (an insertion just half way in); the last motion is continued for ``extend_steps``
    so that a re-targeted copy completes instead of stopping at that threshold.
    """
    positions, quats = commanded_path(episode)
    grasp, handover = keyframes(episode, releases_object)
    handover = min(handover, len(positions) - 1)
    start_yaw = yaw_of(quats[0])
    source_nominal, target_nominal = (
        grasp_yaw(config.object[2], grasp_period, grasp_yaw_offset, start_yaw)
        for config in (source, target)
    )
    at_object = PlanarMotion.between(source.object, target.object, target_nominal - source_nominal)
    at_target = PlanarMotion.between(source.target, target.target)
    near_grasp = np.linalg.norm(positions - positions[grasp], axis=1) < NEAR
    near_handover = np.linalg.norm(positions - positions[handover], axis=1) < NEAR
    # Blend windows: from the start until close to the grasp, and from leaving the grasp
    # until close to the hand-over. Inside NEAR the motion is exactly object- (or target-)
    # relative, so final approaches stay straight.
    reach_object = int(np.flatnonzero(near_grasp[: grasp + 1])[0])
    leave_object = (
        grasp + int(np.argmin(near_grasp[grasp:])) if not near_grasp[grasp:].all() else grasp
    )
    reach_target = leave_object + int(np.argmax(near_handover[leave_object:]))
    new_positions, new_quats = [], []
    steps = len(positions)
    for t in range(steps):
        if t <= leave_object:
            w = min(1.0, t / max(reach_object, 1))
            p = positions[t] + w * (at_object.apply(positions[t]) - positions[t])
            q = _slerp(quats[t], quat_mul(at_object.tool_quat, quats[t]), w)
        else:
            v = min(1.0, (t - leave_object) / max(reach_target - leave_object, 1))
            p = (1 - v) * at_object.apply(positions[t]) + v * at_target.apply(positions[t])
            q = _slerp(
                quat_mul(at_object.tool_quat, quats[t]), quat_mul(at_target.tool_quat, quats[t]), v
            )
        new_positions.append(p)
        new_quats.append(q)
    actions = np.zeros((steps - 1, 7), np.float32)
    for t in range(steps - 1):
        actions[t, :3] = new_positions[t + 1] - new_positions[t]
        actions[t, 3:6] = quat_to_rotvec(quat_mul(new_quats[t + 1], quat_conj(new_quats[t])))
        actions[t, 6] = episode.data[ACTION][t, 6]
    return np.vstack([actions, np.repeat(actions[-1:], extend_steps, axis=0)])


def _slerp(a: np.ndarray, b: np.ndarray, fraction: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions (shortest arc)."""
    delta = quat_mul(b, quat_conj(a))
    step = rotvec_to_quat(quat_to_rotvec(delta) * fraction)
    return quat_mul(step, a)
