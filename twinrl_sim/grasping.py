"""Antipodal grasp sampling for the parallel-jaw gripper, on the object's own geometry.

A top-down grasp is a tool yaw and a closing line at some height through the object.
For each sample the two finger directions are ray-cast against the scene: both rays
must hit the object first (nothing else in the way), the surface normals at the two
hits must oppose each other within the friction cone, and the width must fit the
gripper. Candidates are ranked by antipodal quality, closeness to the object's centre
and how little the wrist has to turn.

Grasps are expressed in the object's frame (``T_grasp``), so that ``T0 * T_grasp`` is
the TCP pose at pick-up and ``T_target * T_grasp`` the TCP pose at placement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_sim.cell import Cell
from twinrl_sim.robots import gripper as gripper_lib


@dataclass(frozen=True)
class Grasp:
    """A top-down grasp in the object's frame.

    Attributes:
        position: TCP position in the object frame (m).
        yaw: tool yaw relative to the object's heading (rad).
        width: distance between the two contacts (m).
        quality: antipodal quality in [0, 1] (1: both normals along the closing line).
        score: ranking score (higher is better).
    """

    position: np.ndarray
    yaw: float
    width: float
    quality: float
    score: float


def _ray(cell: Cell, start: np.ndarray, direction: np.ndarray) -> tuple[float, int, np.ndarray]:
    """First surface of anything along the ray: distance, geom id, normal."""
    geom = np.array([-1], dtype=np.int32)
    normal = np.zeros(3)
    distance = mujoco.mj_ray(cell.model, cell.data, start, direction, None, 1, -1, geom, normal)
    return distance, int(geom[0]), normal


def _ray_object(
    cell: Cell, start: np.ndarray, direction: np.ndarray, geoms: set[int]
) -> tuple[float, int, np.ndarray]:
    """First surface of the object's own geoms along the ray (others are ignored)."""
    model, data = cell.model, cell.data
    best = (-1.0, -1, np.zeros(3))
    for g in geoms:
        normal = np.zeros(3)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            distance = mujoco.mj_rayMesh(model, data, g, start, direction, normal)
        else:
            distance = mujoco.mju_rayGeom(
                data.geom_xpos[g],
                data.geom_xmat[g],
                model.geom_size[g],
                start,
                direction,
                int(model.geom_type[g]),
                normal,
            )
        if distance >= 0 and (best[0] < 0 or distance < best[0]):
            best = (distance, g, normal)
    return best


def sample_antipodal_grasps(
    cell: Cell,
    object_name: str,
    rng: np.random.Generator,
    *,
    samples: int = 200,
    friction_angle: float = math.radians(12),
    reference_yaw: float = 0.0,
    min_clearance: float = 0.008,
) -> list[Grasp]:
    """Ranked antipodal top-down grasps of ``object_name`` in the cell's current state.

    ``reference_yaw`` is the tool yaw (world frame) to stay near, e.g. the current one
    or the task's nominal grasp: grasps that turn the wrist less from it (up to the
    gripper's half turn) rank higher. ``min_clearance`` keeps the fingertips above the
    table.
    """
    model, data = cell.model, cell.data
    mujoco.mj_forward(model, data)
    body = model.body(object_name).id
    object_geoms = {
        g for g in range(model.ngeom) if model.geom_bodyid[g] == body and model.geom_contype[g]
    }
    center, quat = cell.object_pose(object_name)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    rot = rot.reshape(3, 3)
    object_yaw = math.atan2(rot[1, 0], rot[0, 0])
    radius = max(
        float(np.linalg.norm(data.geom_xpos[g][:2] - center[:2]) + model.geom_rbound[g])
        for g in object_geoms
    )
    bottom, top = vertical_extent(cell, object_geoms)
    table = cell.table_top
    pad_tip_below_tcp = 0.003
    max_width = 2 * gripper_lib.STROKE - 0.006
    grasps = []
    for _ in range(samples):
        yaw_world = rng.uniform(-math.pi, math.pi)
        closing = np.array([-math.sin(yaw_world), math.cos(yaw_world), 0.0])  # tool y axis
        along = np.array([math.cos(yaw_world), math.sin(yaw_world), 0.0])
        low = max(bottom, table) + min_clearance + pad_tip_below_tcp
        height = rng.uniform(low, max(low, top - 0.004))
        shift = rng.uniform(-radius, radius) * 0.6
        line = np.array([center[0], center[1], height]) + shift * along
        hits = []
        patch = 0.0
        for sign in (1.0, -1.0):
            start = line + sign * (radius + 0.05) * closing
            distance, _, normal = _ray_object(cell, start, -sign * closing, object_geoms)
            if distance < 0:
                break
            contact = start - sign * distance * closing
            # The finger needs room beside the contact: nothing else within FINGER_ROOM.
            room, _, _ = _ray(cell, contact + sign * 0.001 * closing, sign * closing)
            if 0 <= room < FINGER_ROOM:
                break
            hits.append((contact, normal))
            patch += _flatness(cell, start, -sign * closing, distance, along, object_geoms) / 2
        if len(hits) != 2:
            continue
        (p1, n1), (p2, n2) = hits
        width = float(np.dot(p1 - p2, closing))
        if not 0.0 < width <= max_width:
            continue
        quality = min(float(np.dot(n1, closing)), float(-np.dot(n2, closing)))
        if quality < math.cos(friction_angle):
            continue
        middle = 0.5 * (p1 + p2)
        tcp = np.array([middle[0], middle[1], height])
        yaw_relative = _wrap(yaw_world - object_yaw)
        turn = abs(_wrap(yaw_world - reference_yaw, math.pi))  # the gripper is symmetric
        centrality = float(np.linalg.norm((tcp - center)[:2])) / max(radius, 1e-6)
        depth = (top - height) / max(top - bottom, 1e-6)  # prefer gripping well into the object
        score = 8.0 * quality + 1.0 * patch - 0.5 * centrality - 0.3 * turn + 0.3 * min(depth, 1.0)
        local = rot.T @ (tcp - center)
        grasps.append(
            Grasp(position=local, yaw=yaw_relative, width=width, quality=quality, score=score)
        )
    grasps.sort(key=lambda g: g.score, reverse=True)
    return grasps


FINGER_ROOM = 0.02  # m of free space a finger pad needs beside its contact
PATCH_OFFSET = 0.005  # m: how far around a contact the pad should find the same surface


def _flatness(
    cell: Cell,
    start: np.ndarray,
    direction: np.ndarray,
    distance: float,
    along: np.ndarray,
    geoms: set[int],
) -> float:
    """Share of four neighbouring rays (up, down, fore, aft) that meet the object at the
    same depth: 1 for a flat face under the pad, lower for edges, columns and curves."""
    up = np.array([0.0, 0.0, 1.0])
    found = 0
    for offset in (
        PATCH_OFFSET * up,
        -PATCH_OFFSET * up,
        PATCH_OFFSET * along,
        -PATCH_OFFSET * along,
    ):
        d, geom, _ = _ray_object(cell, start + offset, direction, geoms)
        found += geom in geoms and abs(d - distance) < 0.001
    return found / 4


def vertical_extent(cell: Cell, geoms: set[int]) -> tuple[float, float]:
    """Lowest and highest world z of the geoms' bounding boxes."""
    lows, highs = [], []
    for g in geoms:
        center, half = cell.model.geom_aabb[g][:3], cell.model.geom_aabb[g][3:]
        rot = cell.data.geom_xmat[g].reshape(3, 3)
        z = cell.data.geom_xpos[g][2] + rot[2] @ center
        reach = float(np.abs(rot[2]) @ half)
        lows.append(z - reach)
        highs.append(z + reach)
    return min(lows), max(highs)


def _wrap(angle: float, period: float = 2 * math.pi) -> float:
    return (angle + period / 2) % period - period / 2
