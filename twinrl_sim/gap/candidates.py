"""The effects the gap workflow can name, and how each is fitted.

Plain data, apart from the fitting machinery, so that the command line can list the
candidates without loading ``mujoco.sysid``.
"""

from __future__ import annotations

from dataclasses import dataclass

from twinrl_sim.effects import EFFECTS, PAYLOAD_COG

IMAGE_EFFECTS = ("camera_pose", "appearance")  # fitted on images, not motion


Value = float | tuple[float, ...] | None


@dataclass(frozen=True)
class Fitted:
    """One fitted parameter of an effect.

    ``scale`` is the physical size of one optimiser unit (so that every parameter is
    of order one for the optimiser), ``start`` where the fit starts and ``null`` the
    value that means "no effect"; ``None`` for either is the scene's nominal value.
    """

    effect: str
    param: str
    scale: float
    start: Value
    null: Value

    @property
    def per_joint(self) -> bool:
        return EFFECTS[self.effect].params[self.param].kind == "per_joint"

    @property
    def vector(self) -> bool:
        """Whether the parameter has several components (per joint, or x y z)."""
        return EFFECTS[self.effect].params[self.param].kind in ("per_joint", "vec3")

    def bounds(self) -> tuple[float, float]:
        p = EFFECTS[self.effect].params[self.param]
        return p.low, p.high


@dataclass(frozen=True)
class Candidate:
    """How one effect of the library is fitted: its first parameter as ``scale``,
    ``start`` and ``null`` say (see :class:`Fitted`), and any ``more`` of them with it
    (a payload's centre of gravity with its mass)."""

    effect: str
    scale: float
    start: Value
    null: Value
    needs: str  # "arm": any motion; "torque": joint torques logged; "objects": object
    # poses logged; "grasp": a closed gripper
    more: tuple[tuple[str, float, Value, Value], ...] = ()  # (param, scale, start, null)

    @property
    def fitted(self) -> tuple[Fitted, ...]:
        first = next(iter(EFFECTS[self.effect].params))
        rows = [(first, self.scale, self.start, self.null), *self.more]
        return tuple(Fitted(self.effect, *row) for row in rows)


CANDIDATES: dict[str, Candidate] = {
    c.effect: c
    for c in (
        Candidate("actuator_delay", 0.05, 0.01, 0.0, "arm"),
        Candidate("joint_friction", 5.0, 0.2, 0.0, "arm"),
        Candidate("joint_damping", 5.0, 0.2, 0.0, "arm"),
        Candidate("joint_armature", 0.1, 0.01, 0.0, "arm"),
        Candidate("servo_gain", 1.0, 1.0, 1.0, "arm"),
        Candidate("servo_lead", 0.02, 0.02, 0.0, "arm"),
        Candidate("payload", 1.0, 0.1, 0.0, "arm", more=(("cog", 0.05, PAYLOAD_COG, PAYLOAD_COG),)),
        Candidate("link_mass", 0.1, 1.0, 1.0, "torque"),
        Candidate("link_com", 0.02, 0.0, 0.0, "torque"),
        Candidate("torque_offset", 1.0, 0.0, 0.0, "torque"),
        Candidate("joint_offset", 0.01, 0.0, 0.0, "arm"),
        Candidate("tool_offset", 0.01, 0.0, 0.0, "arm"),
        Candidate("base_offset", 0.01, 0.0, 0.0, "arm"),
        Candidate("object_mass", 1.0, 1.0, 1.0, "grasp"),
        Candidate("object_friction", 0.5, None, None, "grasp"),
        Candidate("table_height", 0.01, 0.0, 0.0, "objects"),
        Candidate("gripper_force", 1.0, 1.0, 1.0, "grasp"),
    )
}
"""Every effect of the library fitted on motion residuals (``camera_pose`` is fitted on
image residuals, by :mod:`twinrl_sim.gap.camera`)."""
