"""Named, parameterised physical effects that a twin may lack and a real cell has.

Each effect is a small edit of a ``mujoco.MjSpec`` before compilation, with units,
bounds and a docstring saying what it models. The plant applies effects as hidden
truth; the gap workflow fits them; a scene spec lists the identified ones under
``effects:``. The file format (an effects YAML) is a mapping ``name: {param: value}``::

    actuator_delay: {seconds: 0.03}
    joint_friction: {coulomb: [1.5, 1.5, 1.0, 0.3, 0.3, 0.3]}
    payload: {mass: 0.8, cog: [0.0, 0.03, 0.05]}
    torque_offset: {torque: [0, -2.5, -1.0, 0, 0, 0]}

Parameter names are part of the public contract: do not rename them. A parameter with a
default may be left out.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import mujoco
import numpy as np
import yaml

from twinrl_sim.errors import TwinError
from twinrl_sim.layout import MOUNT_BODY
from twinrl_sim.servo import feeds_forward, scale_stiffness, set_lead, spec_lead

if TYPE_CHECKING:
    from twinrl_sim.layout import CellLayout


@dataclass(frozen=True)
class ParamDef:
    """One parameter of an effect: its kind, unit and the bounds of each value."""

    kind: Literal["float", "per_joint", "str", "vec3"]
    unit: str
    low: float = -math.inf
    high: float = math.inf
    doc: str = ""
    default: float | tuple[float, ...] | None = None  # what the edit takes when left out;
    # None: the parameter is required


PAYLOAD_COG = (0.0, 0.0, 0.02)  # m, flange frame: where a payload sits unless told
TORQUE_OFFSET_NUMERIC = "twinrl_torque_offset"  # N m per arm joint, added to logged torques

ApplyFn = Callable[..., None]
"""``apply(spec, layout, **params)`` edits ``spec`` in place; ``layout`` names the cell's parts."""


@dataclass(frozen=True)
class EffectDef:
    """A named physical effect and the spec edit that adds it to a model."""

    name: str
    params: dict[str, ParamDef]
    apply: ApplyFn
    doc: str


def _arm_joints(spec: mujoco.MjSpec, layout: CellLayout, values: list[float], what: str):
    if len(values) != len(layout.arm_joints):
        raise TwinError(
            f"{what} needs {len(layout.arm_joints)} values (one per arm joint "
            f"{', '.join(layout.arm_joints)}), got {len(values)}"
        )
    return [spec.joint(name) for name in layout.arm_joints]


def apply_actuator_delay(spec: mujoco.MjSpec, layout: CellLayout, seconds: float) -> None:
    """Command-to-motion latency: each arm servo acts on the target sent ``seconds`` ago.

    The servo's command history is interpolated linearly, so that the delay is exactly
    ``seconds`` at every step (a zero-order hold would round it to whole physics steps,
    differently as floating-point time accumulates).
    """
    if seconds <= 0:
        return
    nsample = math.ceil(seconds / spec.option.timestep) + 2
    for name in layout.arm_actuators:
        act = spec.actuator(name)
        act.delay = seconds
        act.nsample = nsample
        act.interp = 1


def apply_servo_lead(spec: mujoco.MjSpec, layout: CellLayout, seconds: float) -> None:
    """Velocity feed-forward: the arm's servos move their setpoint smoothly from target to
    target and lead it by ``seconds`` more of its speed (:mod:`twinrl_sim.servo`); on a
    twin whose servos hold each target, a non-zero lead makes them track."""
    if seconds == 0:
        return
    set_lead(spec, layout, (spec_lead(spec) or 0.0) + seconds)


def apply_joint_friction(spec: mujoco.MjSpec, layout: CellLayout, coulomb: list[float]) -> None:
    """Dry (Coulomb) friction torque in each arm joint's gearbox, added to the nominal."""
    for joint, value in zip(
        _arm_joints(spec, layout, coulomb, "joint_friction.coulomb"), coulomb, strict=True
    ):
        joint.frictionloss = joint.frictionloss + value


def apply_joint_damping(spec: mujoco.MjSpec, layout: CellLayout, viscous: list[float]) -> None:
    """Viscous friction torque proportional to joint speed, added to the nominal."""
    for joint, value in zip(
        _arm_joints(spec, layout, viscous, "joint_damping.viscous"), viscous, strict=True
    ):
        joint.damping = joint.damping + value


def apply_joint_armature(spec: mujoco.MjSpec, layout: CellLayout, inertia: list[float]) -> None:
    """Reflected rotor inertia (motor and gearbox) per arm joint, added to the nominal:
    torque the joint takes to accelerate that the links' inertia does not explain."""
    for joint, value in zip(
        _arm_joints(spec, layout, inertia, "joint_armature.inertia"), inertia, strict=True
    ):
        joint.armature = joint.armature + value


def apply_servo_gain(spec: mujoco.MjSpec, layout: CellLayout, scale: list[float]) -> None:
    """Position-servo stiffness of each arm joint relative to the nominal gain."""
    _arm_joints(spec, layout, scale, "servo_gain.scale")
    for name, value in zip(layout.arm_actuators, scale, strict=True):
        scale_stiffness(spec.actuator(name), value)


def apply_payload(
    spec: mujoco.MjSpec, layout: CellLayout, mass: float, cog: Sequence[float] = PAYLOAD_COG
) -> None:
    """A load (tool, cable) of ``mass`` kg carried at the flange, its centre of gravity
    at ``cog`` (m, flange frame), as a pendant's payload setting holds them. Servos that
    feed the model forward carry it as a UR does with its payload set; servos that hold
    sag under it."""
    if mass <= 0:
        return
    body = spec.body(layout.flange_body).add_body(name="effect_payload", pos=list(cog))
    body.explicitinertial = True
    body.mass = mass
    body.inertia = [mass * 1e-3] * 3
    body.gravcomp = 1.0 if feeds_forward(spec) else 0.0


def apply_link_mass(spec: mujoco.MjSpec, layout: CellLayout, scale: list[float]) -> None:
    """The mass of the link each arm joint turns, as a multiple of the twin's (its inertia
    scaled alike, its centre of mass kept): an error in the arm's gravity model."""
    for joint, value in zip(
        _arm_joints(spec, layout, scale, "link_mass.scale"), scale, strict=True
    ):
        body = joint.parent
        if not body.explicitinertial:  # the mass comes from the link's geoms
            for geom in body.geoms:
                geom.mass, geom.density = geom.mass * value, geom.density * value
            continue
        body.mass = body.mass * value
        body.inertia = np.asarray(body.inertia, float) * value
        body.fullinertia = np.asarray(body.fullinertia, float) * value


def apply_link_com(spec: mujoco.MjSpec, layout: CellLayout, shift: list[float]) -> None:
    """The centre of mass of the link each arm joint turns, moved ``shift`` metres along
    the link (towards the next joint; for the last link, away from its joint along its
    axis): the other half of an error in the arm's gravity model."""
    for joint, value in zip(_arm_joints(spec, layout, shift, "link_com.shift"), shift, strict=True):
        if value == 0:
            continue
        body = joint.parent
        body.ipos = np.asarray(body.ipos, float) + value * link_direction(body, joint)


def link_direction(body: mujoco.MjsBody, joint: mujoco.MjsJoint) -> np.ndarray:
    """Unit vector along a link, in its frame: to its first child body, or the joint's
    axis where the child sits on it."""
    axis = np.asarray(joint.axis, float) / np.linalg.norm(joint.axis)
    children = body.find_all(mujoco.mjtObj.mjOBJ_BODY)
    if children:
        offset = np.asarray(children[0].pos, float) - np.asarray(joint.pos, float)
        offset -= axis * (offset @ axis)  # along the axis moves no torque of this joint
        if np.linalg.norm(offset) > 1e-6:
            return offset / np.linalg.norm(offset)
    return axis


def apply_torque_offset(spec: mujoco.MjSpec, layout: CellLayout, torque: list[float]) -> None:
    """A constant offset in each arm joint's logged torque (N m): a drive's current
    offset, or a steady torque the controller's model adds (a cable's pull it counters).
    It changes what the joints log, not how they move."""
    _arm_joints(spec, layout, torque, "torque_offset.torque")
    numeric = next((n for n in spec.numerics if n.name == TORQUE_OFFSET_NUMERIC), None)
    if numeric is None:
        spec.add_numeric(name=TORQUE_OFFSET_NUMERIC, data=list(torque), size=len(torque))
    else:
        numeric.data = list(np.asarray(numeric.data, float) + np.asarray(torque, float))


def torque_offset(model: mujoco.MjModel, joints: int) -> np.ndarray:
    """The ``torque_offset`` effect's offsets in ``model`` (zeros without one)."""
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, TORQUE_OFFSET_NUMERIC)
    if index < 0:
        return np.zeros(joints)
    start = model.numeric_adr[index]
    return model.numeric_data[start : start + joints].copy()


def apply_object_mass(spec: mujoco.MjSpec, layout: CellLayout, scale: float) -> None:
    """The manipulated object's mass, as a multiple of its nominal mass."""
    for geom in _object_geoms(spec, layout):
        geom.density = geom.density * scale


def apply_object_friction(spec: mujoco.MjSpec, layout: CellLayout, sliding: float) -> None:
    """Sliding friction coefficient of the manipulated object's contacts."""
    for geom in _object_geoms(spec, layout):
        friction = np.array(geom.friction)
        friction[0] = sliding
        geom.friction = friction


def apply_table_height(spec: mujoco.MjSpec, layout: CellLayout, offset: float) -> None:
    """The table top is ``offset`` metres higher than nominal (objects rest on it)."""
    body = spec.body(layout.table_body)
    body.pos = np.array(body.pos) + [0.0, 0.0, offset]


def apply_tool_offset(spec: mujoco.MjSpec, layout: CellLayout, xyz: list[float]) -> None:
    """The tool centre point the robot reports sits ``xyz`` (m) from the twin's, in the
    frame of the body that carries it: a tool, or a TCP setting, the twin lacks."""
    site = spec.site(layout.tcp_site)
    site.pos = np.asarray(site.pos) + np.asarray(xyz, float)


def apply_base_offset(spec: mujoco.MjSpec, layout: CellLayout, xyz: list[float]) -> None:
    """The arm's base stands ``xyz`` (m, world frame) from where the twin has it: mounted
    elsewhere on its stand or table than the scene says. Joint motion is unchanged; the
    tool, and what it touches, are shifted."""
    body = spec.body(MOUNT_BODY)
    body.pos = np.asarray(body.pos) + np.asarray(xyz, float)


def apply_joint_offset(spec: mujoco.MjSpec, layout: CellLayout, radians: list[float]) -> None:
    """Encoder calibration error: the measured angle is the true angle plus ``radians``.

    Each link downstream of a hinge is turned back by the offset about the hinge axis,
    so that the joint coordinate (what the encoder and the servo see) reads
    ``true + offset``.
    """
    for joint, offset in zip(
        _arm_joints(spec, layout, radians, "joint_offset.radians"), radians, strict=True
    ):
        if offset == 0:
            continue
        body = joint.parent
        axis = np.asarray(joint.axis, float)
        axis /= np.linalg.norm(axis)
        pivot = np.asarray(joint.pos, float)
        turn = np.zeros(4)
        mujoco.mju_axisAngle2Quat(turn, axis, -offset)
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, turn)
        shift = pivot - rot.reshape(3, 3) @ pivot
        body_quat = np.asarray(body.quat, float)
        body_quat /= np.linalg.norm(body_quat)
        body_rot = np.zeros(9)
        mujoco.mju_quat2Mat(body_rot, body_quat)
        body.pos = np.asarray(body.pos) + body_rot.reshape(3, 3) @ shift
        new_quat = np.zeros(4)
        mujoco.mju_mulQuat(new_quat, body_quat, turn)
        body.quat = new_quat


def apply_camera_pose(
    spec: mujoco.MjSpec,
    layout: CellLayout,
    camera: str,
    xyz: list[float],
    rpy: list[float],
) -> None:
    """Camera mounting error: position offset (m) and roll/pitch/yaw (rad) in its frame."""
    if camera not in layout.cameras:
        close = difflib.get_close_matches(camera, layout.cameras, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise TwinError(f"camera_pose.camera '{camera}' is not a camera of this cell{hint}")
    cam = spec.camera(camera)
    quat = np.asarray(cam.quat, float)
    quat /= np.linalg.norm(quat)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    cam.pos = np.asarray(cam.pos) + rot.reshape(3, 3) @ np.asarray(xyz, float)
    turn = np.zeros(4)
    mujoco.mju_euler2Quat(turn, np.asarray(rpy, float), "xyz")
    new_quat = np.zeros(4)
    mujoco.mju_mulQuat(new_quat, quat, turn)
    cam.quat = new_quat


def apply_gripper_force(spec: mujoco.MjSpec, layout: CellLayout, scale: float) -> None:
    """The gripper's maximum closing force relative to nominal."""
    if layout.gripper_actuator is None:
        raise TwinError("gripper_force needs a gripper; this cell has none")
    act = spec.actuator(layout.gripper_actuator)
    act.forcerange = np.asarray(act.forcerange) * scale


def apply_appearance(
    spec: mujoco.MjSpec, layout: CellLayout, light_scale: float, table_tint: list[float]
) -> None:
    """How the cell looks: light intensity relative to nominal and a colour offset of the
    table top (what cameras see differently; no effect on motion).

    ``light_scale`` multiplies the diffuse colour of the cell's lights (not the
    renderer's headlight), each channel capped at 1; ``table_tint`` (RGB, 0-1 scale) is
    added to the table top's colour, and to the two colours of its texture if it has one.
    """
    for light in spec.lights:
        light.diffuse = np.minimum(1.0, np.asarray(light.diffuse) * light_scale)
    tint = np.asarray(table_tint, float)
    geom = spec.geom(layout.table_geom)
    rgba = np.asarray(geom.rgba, float)
    geom.rgba = np.r_[np.clip(rgba[:3] + tint, 0, 1), rgba[3]]
    if geom.material:
        role = mujoco.mjtTextureRole.mjTEXROLE_RGB
        texture = spec.texture(spec.material(geom.material).textures[role])
        texture.rgb1 = np.clip(np.asarray(texture.rgb1) + tint, 0, 1)
        texture.rgb2 = np.clip(np.asarray(texture.rgb2) + 0.6 * tint, 0, 1)


def _object_geoms(spec: mujoco.MjSpec, layout: CellLayout) -> list[mujoco.MjsGeom]:
    if not layout.manipulated:
        raise TwinError("this cell has no manipulated object")
    geoms = []
    for name in layout.manipulated:
        geoms.extend(g for g in spec.body(name).geoms if g.contype or g.conaffinity)
    return geoms


_PER_JOINT = "per_joint"
EFFECTS: dict[str, EffectDef] = {
    d.name: d
    for d in (
        EffectDef(
            "actuator_delay",
            {"seconds": ParamDef("float", "s", 0.0, 0.5, "command-to-motion latency")},
            apply_actuator_delay,
            apply_actuator_delay.__doc__ or "",
        ),
        EffectDef(
            "servo_lead",
            {"seconds": ParamDef("float", "s", -0.2, 0.5, "servo velocity feed-forward")},
            apply_servo_lead,
            apply_servo_lead.__doc__ or "",
        ),
        EffectDef(
            "joint_friction",
            {"coulomb": ParamDef(_PER_JOINT, "N m", 0.0, 50.0, "dry friction per arm joint")},
            apply_joint_friction,
            apply_joint_friction.__doc__ or "",
        ),
        EffectDef(
            "joint_damping",
            {"viscous": ParamDef(_PER_JOINT, "N m s/rad", 0.0, 200.0, "viscous friction")},
            apply_joint_damping,
            apply_joint_damping.__doc__ or "",
        ),
        EffectDef(
            "joint_armature",
            {"inertia": ParamDef(_PER_JOINT, "kg m^2", 0.0, 5.0, "rotor inertia per joint")},
            apply_joint_armature,
            apply_joint_armature.__doc__ or "",
        ),
        EffectDef(
            "servo_gain",
            {"scale": ParamDef(_PER_JOINT, "x nominal", 0.01, 10.0, "servo stiffness")},
            apply_servo_gain,
            apply_servo_gain.__doc__ or "",
        ),
        EffectDef(
            "payload",
            {
                "mass": ParamDef("float", "kg", 0.0, 20.0, "load at the flange"),
                "cog": ParamDef(
                    "vec3",
                    "m",
                    -0.3,
                    0.3,
                    "its centre of gravity, flange frame",
                    default=tuple(PAYLOAD_COG),
                ),
            },
            apply_payload,
            apply_payload.__doc__ or "",
        ),
        EffectDef(
            "link_mass",
            {"scale": ParamDef(_PER_JOINT, "x nominal", 0.2, 5.0, "mass of each joint's link")},
            apply_link_mass,
            apply_link_mass.__doc__ or "",
        ),
        EffectDef(
            "link_com",
            {"shift": ParamDef(_PER_JOINT, "m", -0.3, 0.3, "centre of mass along each link")},
            apply_link_com,
            apply_link_com.__doc__ or "",
        ),
        EffectDef(
            "torque_offset",
            {"torque": ParamDef(_PER_JOINT, "N m", -100.0, 100.0, "logged torque offset")},
            apply_torque_offset,
            apply_torque_offset.__doc__ or "",
        ),
        EffectDef(
            "object_mass",
            {"scale": ParamDef("float", "x nominal", 0.01, 20.0, "object mass")},
            apply_object_mass,
            apply_object_mass.__doc__ or "",
        ),
        EffectDef(
            "object_friction",
            {"sliding": ParamDef("float", "", 0.01, 5.0, "sliding friction coefficient")},
            apply_object_friction,
            apply_object_friction.__doc__ or "",
        ),
        EffectDef(
            "table_height",
            {"offset": ParamDef("float", "m", -0.2, 0.2, "table top height error")},
            apply_table_height,
            apply_table_height.__doc__ or "",
        ),
        EffectDef(
            "joint_offset",
            {"radians": ParamDef(_PER_JOINT, "rad", -0.5, 0.5, "encoder offset per joint")},
            apply_joint_offset,
            apply_joint_offset.__doc__ or "",
        ),
        EffectDef(
            "tool_offset",
            {"xyz": ParamDef("vec3", "m", -0.3, 0.3, "TCP offset in the tool body's frame")},
            apply_tool_offset,
            apply_tool_offset.__doc__ or "",
        ),
        EffectDef(
            "base_offset",
            {"xyz": ParamDef("vec3", "m", -0.3, 0.3, "arm base mounting error, world frame")},
            apply_base_offset,
            apply_base_offset.__doc__ or "",
        ),
        EffectDef(
            "camera_pose",
            {
                "camera": ParamDef("str", "", doc="camera name"),
                "xyz": ParamDef("vec3", "m", -1.0, 1.0, "position offset"),
                "rpy": ParamDef("vec3", "rad", -math.pi, math.pi, "orientation offset"),
            },
            apply_camera_pose,
            apply_camera_pose.__doc__ or "",
        ),
        EffectDef(
            "appearance",
            {
                "light_scale": ParamDef("float", "x nominal", 0.05, 3.0, "light intensity"),
                "table_tint": ParamDef("vec3", "rgb", -1.0, 1.0, "table colour offset"),
            },
            apply_appearance,
            apply_appearance.__doc__ or "",
        ),
        EffectDef(
            "gripper_force",
            {"scale": ParamDef("float", "x nominal", 0.0, 10.0, "gripper force")},
            apply_gripper_force,
            apply_gripper_force.__doc__ or "",
        ),
    )
}


def validate_effects(effects: Any) -> dict[str, dict[str, Any]]:
    """Check names, parameter names, types and bounds; raise one ``ValueError`` listing all.

    Returns the effects with every value converted to plain floats/lists.
    """
    if not isinstance(effects, dict):
        raise TwinError(
            f"effects must be a mapping name: {{param: value}}, got {type(effects).__name__}"
        )
    problems: list[str] = []
    clean: dict[str, dict[str, Any]] = {}
    for name, params in effects.items():
        definition = EFFECTS.get(name)
        if definition is None:
            close = difflib.get_close_matches(str(name), list(EFFECTS), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            problems.append(f"unknown effect '{name}'{hint}; known: {', '.join(EFFECTS)}")
            continue
        if not isinstance(params, dict):
            problems.append(f"{name}: expected a mapping of parameters, got {params!r}")
            continue
        required = {k for k, p in definition.params.items() if p.default is None}
        missing = sorted(required - set(params))
        extra = sorted(set(params) - set(definition.params))
        if missing:
            problems.append(f"{name}: missing parameter(s) {', '.join(missing)}")
        for key in extra:
            close = difflib.get_close_matches(key, list(definition.params), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            problems.append(f"{name}: unknown parameter '{key}'{hint}")
        clean[name] = {}
        for key, pdef in definition.params.items():
            if key in params:
                value, problem = _check_value(pdef, params[key])
                if problem:
                    problems.append(f"{name}.{key}: {problem}")
                clean[name][key] = value
    if problems:
        raise TwinError("; ".join(problems))
    return clean


def _check_value(pdef: ParamDef, value: Any) -> tuple[Any, str | None]:
    if pdef.kind == "str":
        return value, None if isinstance(value, str) else f"expected a name, got {value!r}"
    values = value if isinstance(value, list | tuple) else [value]
    if pdef.kind == "float" and isinstance(value, list | tuple):
        return value, f"expected one number ({pdef.unit}), got a list"
    if pdef.kind == "vec3" and len(values) != 3:
        return value, f"expected 3 numbers ({pdef.unit}), got {len(values)}"
    if pdef.kind == _PER_JOINT and not isinstance(value, list | tuple):
        return value, f"expected one number per arm joint ({pdef.unit}), got {value!r}"
    try:
        numbers = [float(v) for v in values]
    except (TypeError, ValueError):
        return value, f"expected numbers ({pdef.unit}), got {value!r}"
    bad = [v for v in numbers if not (pdef.low <= v <= pdef.high) or not math.isfinite(v)]
    if bad:
        unit = f" {pdef.unit}" if pdef.unit else ""
        return value, f"{bad[0]} is outside [{pdef.low}, {pdef.high}]{unit}"
    return (numbers[0] if pdef.kind == "float" else numbers), None


def apply_effects(
    spec: mujoco.MjSpec, layout: CellLayout, effects: dict[str, dict[str, Any]]
) -> None:
    """Apply validated effects to ``spec`` in a fixed order (the order of :data:`EFFECTS`)."""
    clean = validate_effects(effects)
    for name, definition in EFFECTS.items():
        if name in clean:
            definition.apply(spec, layout, **clean[name])


def load_effects(path: str | Path) -> dict[str, dict[str, Any]]:
    """Read and validate an effects YAML file (``name: {param: value}``)."""
    path = Path(path)
    if not path.is_file():
        raise TwinError(f"effects file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise TwinError(f"{path}: not valid YAML ({err})") from None
    try:
        return validate_effects(data)
    except ValueError as err:
        raise TwinError(f"{path}: {err}") from None


def describe_effects() -> list[tuple[str, str, str]]:
    """(effect, parameters with units and bounds, what it models) for help texts."""
    rows = []
    for d in EFFECTS.values():
        params = ", ".join(
            f"{k} [{p.unit}]" + (f" in [{p.low:g}, {p.high:g}]" if math.isfinite(p.low) else "")
            for k, p in d.params.items()
        )
        rows.append((d.name, params, d.doc.splitlines()[0]))
    return rows
