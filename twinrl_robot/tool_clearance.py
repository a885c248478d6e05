"""What of the tool must stay off the table: the corners of its collision geometry.

The workspace box bounds the tool centre point, but the gripper's fingers reach below it,
and further when the tool tilts: a pad corner 3 mm under the TCP drops 7 mm more at a 10
degree tilt with the fingers open. A real arm whose fingers meet the table at speed, or
press on it, stops for its force limit. The guard therefore keeps every corner of the
tool's collision geoms (their bounding boxes, with the fingers open and closed) a
clearance above the table, whatever the tilt.
"""

from __future__ import annotations

import mujoco
import numpy as np

from twinrl_sim.body_tree import subtree
from twinrl_sim.cell import Cell

_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)


def tool_points(twin: Cell) -> np.ndarray:
    """The corners (n x 3, m, TCP frame) of every colliding geom carried by the flange,
    with the tool's joints (the fingers) at their lower and at their upper limits."""
    model, layout = twin.model, twin.layout
    tool = subtree(model, model.body(layout.flange_body).id)
    colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    geoms = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in tool and colliding[g]]
    joints = [j for j in range(model.njnt) if int(model.jnt_bodyid[j]) in tool]
    data = mujoco.MjData(model)
    data.qpos[twin.arm_qpos] = layout.home_qpos
    site = model.site(layout.tcp_site).id
    points = []
    for end in (0, 1):
        for joint in joints:
            limits = model.jnt_range[joint] if model.jnt_limited[joint] else (0.0, 0.0)
            data.qpos[model.jnt_qposadr[joint]] = limits[end]
        mujoco.mj_kinematics(model, data)
        tcp_rotation = data.site_xmat[site].reshape(3, 3)
        for geom in geoms:
            centre, half = model.geom_aabb[geom, :3], model.geom_aabb[geom, 3:]
            rotation = data.geom_xmat[geom].reshape(3, 3)
            world = data.geom_xpos[geom] + (centre + _CORNERS * half) @ rotation.T
            points.append((world - data.site_xpos[site]) @ tcp_rotation)
    return np.concatenate(points)
