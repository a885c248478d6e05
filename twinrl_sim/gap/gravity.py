"""Which parts of an arm's gravity model joint torques can tell apart.

The torque a joint needs to hold the arm against gravity depends on each link's mass
and centre of mass, and on what the arm carries at its flange. Many of these act alike:
a wrist link's weight pulls where a payload's does, and a link's mass and the position
of its centre of mass along it move the same torques when nothing upstream separates
them. Fitting parameters that act alike spreads one error over all of them (a 2 kg tool
came out as 1.8 kg plus a wrist link three times its weight, explaining the data just
as well), so the gap workflow fits only those the torques can separate.

The test is structural (from the twin's model, before any data): over poses spread
through the joints' range, each parameter's gravity torques form a column; the payload's
mass and centre of gravity come first (what a pendant's payload setting holds, and what
a real tool changes), then each link's mass, heaviest first, then the centres of mass.
A parameter is kept when its column is not within :data:`SEPARABLE` of the span of those
kept before it; the others are reported with what they cannot be told from.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_sim.effects import PAYLOAD_COG, link_direction
from twinrl_sim.layout import CellLayout

GRAVITY_EFFECTS = ("link_mass", "link_com")  # per-joint effects fitted in part
SEPARABLE = 0.1  # share of a column's norm outside the span of those kept before it
POSES = 24  # poses the columns are evaluated at
SPREAD = 1.2  # rad: poses are the home pose plus up to this much on each joint
STEP = 1e-3  # m: finite-difference step of a centre of mass


@dataclass(frozen=True)
class GravityParts:
    """The per-joint components of ``link_mass`` and ``link_com`` that the torques can
    separate, and why each other one is left at the nominal model."""

    link_mass: tuple[int, ...]
    link_com: tuple[int, ...]
    lumped: dict[str, str]  # "link_mass.<joint>" / "link_com.<joint>" -> why not fitted

    def components(self, effect: str) -> tuple[int, ...] | None:
        """The fitted components of ``effect`` (None: every one, not a gravity effect)."""
        return getattr(self, effect) if effect in GRAVITY_EFFECTS else None


def separable_parts(
    spec: mujoco.MjSpec, model: mujoco.MjModel, layout: CellLayout, seed: int = 0
) -> GravityParts:
    """The gravity parameters of the twin ``model`` (compiled from ``spec``) that joint
    torques can tell apart (see the module docstring)."""
    data = mujoco.MjData(model)
    joints = [model.joint(j) for j in layout.arm_joints]
    qpos = [j.qposadr[0] for j in joints]
    dof = [j.dofadr[0] for j in joints]
    links = [model.jnt_bodyid[j.id] for j in joints]
    flange = model.body(layout.flange_body).id
    directions = [
        link_direction(spec.joint(name).parent, spec.joint(name)) for name in layout.arm_joints
    ]
    rng = np.random.default_rng(seed)
    home = np.asarray(layout.home_qpos, float)
    poses = home + rng.uniform(-SPREAD, SPREAD, (POSES, len(home)))
    gravity = model.opt.gravity
    columns: dict[str, list[np.ndarray]] = {}

    def torque(body: int, point: np.ndarray, mass: float) -> np.ndarray:
        jac = np.zeros((3, model.nv))
        mujoco.mj_jac(model, data, jac, None, point, body)
        return -jac[:, dof].T @ (mass * gravity)

    for q in poses:
        data.qpos[qpos] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        rot = data.xmat[flange].reshape(3, 3)
        cog = data.xpos[flange] + rot @ np.asarray(PAYLOAD_COG)
        rows = {"payload.mass": torque(flange, cog, 1.0)}
        for axis, name in enumerate("xyz"):
            moved = cog + rot[:, axis] * STEP
            rows[f"payload.cog.{name}"] = (torque(flange, moved, 1.0) - rows["payload.mass"]) / STEP
        for joint, body, direction in zip(layout.arm_joints, links, directions, strict=True):
            mass = float(model.body_mass[body])
            com = data.xipos[body]
            rows[f"link_mass.{joint}"] = torque(body, com, mass)
            along = data.xmat[body].reshape(3, 3) @ direction
            shifted = torque(body, com + along * STEP, mass)
            rows[f"link_com.{joint}"] = (shifted - rows[f"link_mass.{joint}"]) / STEP
        for name, row in rows.items():
            columns.setdefault(name, []).append(row)
    stacked = {name: np.concatenate(rows) for name, rows in columns.items()}
    heaviest = [layout.arm_joints[i] for i in np.argsort(model.body_mass[links])[::-1]]
    order = [n for n in stacked if n.startswith("payload")]
    order += [f"link_mass.{j}" for j in heaviest] + [f"link_com.{j}" for j in heaviest]
    kept: list[str] = []
    lumped: dict[str, str] = {}
    for name in order:
        column = stacked[name]
        size = np.linalg.norm(column)
        if size < 1e-9:
            lumped[name] = "never loads a joint against gravity"
            continue
        if kept:
            basis = np.stack([stacked[k] for k in kept], axis=1)
            coef, *_ = np.linalg.lstsq(basis, column, rcond=None)
            outside = np.linalg.norm(column - basis @ coef) / size
            if outside < SEPARABLE:
                main = kept[int(np.argmax(np.abs(coef) * np.linalg.norm(basis, axis=0)))]
                lumped[name] = f"acts on the joints as {main} does"
                continue
        kept.append(name)
    joints = layout.arm_joints
    return GravityParts(
        tuple(i for i, j in enumerate(joints) if f"link_mass.{j}" in kept),
        tuple(i for i, j in enumerate(joints) if f"link_com.{j}" in kept),
        lumped,
    )
