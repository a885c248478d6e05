"""Compile a :class:`~twinrl_sim.spec.SceneSpec` into a MuJoCo model through ``MjSpec``.

The result carries a :class:`CellLayout` naming the parts that controllers, tasks and
effects address (arm joints and actuators, flange, TCP site, gripper, table, objects,
cameras), so nothing downstream hard-codes the built-in robot's names.

Movable objects get a free joint; targets and fixtures are mocap bodies, so a task can
place them per episode without recompiling.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from PIL import Image

from twinrl_sim.cubemap import cube_directions, cube_lookup
from twinrl_sim.effects import apply_effects
from twinrl_sim.layout import MOUNT_BODY, CellLayout
from twinrl_sim.robots import gripper as gripper_lib
from twinrl_sim.robots import ur5e
from twinrl_sim.servo import full_lead, set_feedforward, set_lead
from twinrl_sim.spec import CameraSpec, GeomSpec, ObjectSpec, SceneSpec, SpecError

EMPTY_PREFIX_WARNING = "Attaching a spec with an empty prefix"  # MuJoCo's words

FLOOR_DEPTH = 0.75  # floor below the table top (m)
ENV_CONTYPE, ENV_CONAFFINITY = 1, 1
VISUAL_GROUP = 1
UNSEEN_GROUP = 3  # geoms that collide where a picture shows instead (viewers hide group 3)


@dataclass(frozen=True)
class CompiledScene:
    """A compiled model with the spec it came from and its layout."""

    spec: SceneSpec
    model: mujoco.MjModel
    layout: CellLayout


def build_mjspec(
    scene: SceneSpec, *, apply_spec_effects: bool = True
) -> tuple[mujoco.MjSpec, CellLayout]:
    """Assemble the ``MjSpec`` for ``scene`` (effects included unless told otherwise)."""
    spec = mujoco.MjSpec()
    spec.modelname = scene.name
    spec.compiler.degree = False  # every angle in a spec is in radians
    spec.option.timestep = scene.physics.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    # Grasped objects must not creep out of the fingers under soft contacts.
    spec.option.noslip_iterations = 3
    width = max([c.width for c in scene.cameras] + [640])
    height = max([c.height for c in scene.cameras] + [480])
    spec.visual.global_.offwidth = width
    spec.visual.global_.offheight = height
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.4, 0.4, 0.4]

    _add_room(spec, scene)
    arm_joints, arm_actuators, flange, tcp, home = _add_robot(spec, scene)
    has_gripper = scene.robot.gripper == "parallel_jaw"
    if has_gripper:
        gripper_lib.add_parallel_gripper(spec.body(flange), spec)
        tcp = gripper_lib.TCP_SITE
    elif not tcp:  # the bare built-in arm: the tool centre point is the flange itself
        spec.body(flange).add_site(name=gripper_lib.TCP_SITE, group=3)
        tcp = gripper_lib.TCP_SITE
    manipulated, placed = [], []
    for obj in scene.objects:
        _add_object(spec, scene, obj)
        (manipulated if obj.role == "manipulated" else placed).append(obj.name)
    for cam in scene.cameras:
        _add_camera(spec, scene, cam, flange)
    for i, light in enumerate(scene.lights):
        spec.worldbody.add_light(
            name=f"light{i}", pos=light.pos, dir=light.dir, diffuse=light.diffuse, castshadow=False
        )
    layout = CellLayout(
        arm_joints=tuple(arm_joints),
        arm_actuators=tuple(arm_actuators),
        flange_body=flange,
        tcp_site=tcp,
        gripper_actuator=gripper_lib.ACTUATOR if has_gripper else None,
        gripper_joint=gripper_lib.JOINT if has_gripper else None,
        table_body="table",
        table_geom="table_top",
        manipulated=tuple(manipulated),
        placed=tuple(placed),
        cameras=tuple(c.name for c in scene.cameras),
        home_qpos=tuple(home),
    )
    if scene.physics.servo == "track":
        lead = scene.physics.servo_lead
        set_lead(spec, layout, full_lead(spec, layout) if lead is None else lead)
    if scene.physics.feeds_forward:
        set_feedforward(spec, layout)
    if apply_spec_effects and scene.effects:
        try:
            apply_effects(spec, layout, scene.effects)
        except ValueError as err:
            raise SpecError(f"scene '{scene.name}' effects: {err}") from None
    return spec, layout


def compile_scene(scene: SceneSpec, *, extra_effects: dict | None = None) -> CompiledScene:
    """Compile ``scene`` (with ``extra_effects`` on top of its own) to a MuJoCo model."""
    if extra_effects:
        scene = scene.with_effects(extra_effects)
    spec, layout = build_mjspec(scene)
    try:
        with warnings.catch_warnings():
            # A custom robot is attached without a name prefix on purpose (the spec names
            # its joints as they are in its file); the compiled model is never re-saved.
            warnings.filterwarnings("ignore", message=EMPTY_PREFIX_WARNING)
            model = spec.compile()
    except ValueError as err:
        raise SpecError(f"scene '{scene.name}' does not compile in MuJoCo: {err}") from None
    _check_stable(model, scene.name)
    return CompiledScene(spec=scene, model=model, layout=layout)


STABILITY_STEPS = 25  # physics steps a compiled scene must take without diverging


def _check_stable(model: mujoco.MjModel, name: str) -> None:
    """Refuse a model that diverges at once (a NaN, an unstable acceleration)."""
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=STABILITY_STEPS)
    diverged = data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0
    if diverged or not (np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()):
        raise SpecError(
            f"scene '{name}' diverges in simulation within {STABILITY_STEPS} physics steps; "
            "check its objects' positions, sizes and masses and its physics timestep"
        )


def _add_room(spec: mujoco.MjSpec, scene: SceneSpec) -> None:
    table = scene.table
    if scene.backdrop is not None:
        _add_backdrop(spec, scene.backdrop)
    else:
        spec.add_texture(
            name="skybox",
            type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
            rgb1=[0.55, 0.65, 0.75],
            rgb2=[0.1, 0.1, 0.12],
            width=64,
            height=64,
        )
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[3, 3, 0.1],
        pos=[0, 0, table.top_height - FLOOR_DEPTH],
        rgba=[0.3, 0.3, 0.32, 1],
        contype=ENV_CONTYPE,
        conaffinity=ENV_CONAFFINITY,
        group=UNSEEN_GROUP if scene.backdrop is not None else 0,  # the backdrop shows the floor
    )
    body = spec.worldbody.add_body(
        name="table",
        pos=[table.center[0], table.center[1], table.top_height],
        quat=yaw_quat(table.yaw).tolist(),
    )
    material = ""
    if table.image is not None:  # the picture once over the top
        spec.add_texture(
            name="table_texture", type=mujoco.mjtTexture.mjTEXTURE_2D, file=str(table.image)
        )
        repeat = [1, 1]
    elif table.texture != "plain":
        builtin = {
            "checker": mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
            "gradient": mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        }
        spec.add_texture(
            name="table_texture",
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            builtin=builtin[table.texture],
            rgb1=list(table.rgba[:3]),
            rgb2=[0.6 * c for c in table.rgba[:3]],
            width=256,
            height=256,
        )
        repeat = [4, 4]
    if table.image is not None or table.texture != "plain":
        material_spec = spec.add_material(name="table_material", texrepeat=repeat)
        material_spec.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "table_texture"
        material = "table_material"
    body.add_geom(
        material=material,
        name="table_top",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[table.size[0] / 2, table.size[1] / 2, table.thickness / 2],
        pos=[0, 0, -table.thickness / 2],
        rgba=(1.0, 1.0, 1.0, 1.0) if table.image is not None else table.rgba,
        friction=[table.friction, 0.005, 0.0001],
        contype=ENV_CONTYPE,
        conaffinity=ENV_CONAFFINITY,
    )


def _add_backdrop(spec: mujoco.MjSpec, picture: Path) -> None:
    """The skybox from a cube map of the base frame. MuJoCo turns a skybox so that its
    +y face is up: each of its texels takes the backdrop's texel in the direction it
    shows, (x, y, z) of the skybox being (x, -z, y) of the base frame."""
    backdrop = np.asarray(Image.open(picture).convert("RGB"))
    size = backdrop.shape[1]
    if backdrop.shape[0] != 6 * size:
        raise SpecError(
            f"backdrop {picture} is {backdrop.shape[1]}x{backdrop.shape[0]} pixels; a cube map "
            "is six square faces stacked (width x 6*width)"
        )
    shown = cube_directions(size)
    base = np.stack([shown[..., 0], -shown[..., 2], shown[..., 1]], axis=-1)
    texture = spec.add_texture(
        name="skybox",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        width=size,
        height=6 * size,
        nchannel=3,
    )
    texture.data = np.ascontiguousarray(cube_lookup(backdrop, base)).tobytes()


def _add_robot(
    spec: mujoco.MjSpec, scene: SceneSpec
) -> tuple[list[str], list[str], str, str, list[float]]:
    robot = scene.robot
    mount = spec.worldbody.add_body(name=MOUNT_BODY, pos=list(robot.base_pos))
    if robot.is_builtin:
        flange = ur5e.add_ur5e(mount)
        joints = list(ur5e.JOINT_NAMES)
        for i, name in enumerate(joints):
            act = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            act.set_to_position(kp=ur5e.SERVO_KP[i])
            act.ctrlrange = list(ur5e.JOINT_LIMITS[i])
            act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
            limit = ur5e.JOINT_TORQUE_LIMITS[i]
            act.forcerange = [-limit, limit]
            act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        home = list(robot.home_qpos or ur5e.HOME_QPOS)
        return joints, joints, flange.name, "", home
    return _attach_custom_robot(spec, scene, mount)


@contextlib.contextmanager
def _quiet_empty_prefix_warning() -> Iterator[None]:
    """Swallow MuJoCo's printed warning about attaching without a name prefix.

    A custom robot is attached unprefixed on purpose (the spec names its joints as they
    are in its file) and the compiled model is never re-saved; any other MuJoCo warning
    raised meanwhile is passed on as a Python warning.
    """
    previous = mujoco.get_mju_user_warning()

    def handler(message: str) -> None:
        if not message.startswith(EMPTY_PREFIX_WARNING):
            warnings.warn(f"MuJoCo: {message}", stacklevel=2)

    mujoco.set_mju_user_warning(handler)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def _attach_custom_robot(
    spec: mujoco.MjSpec, scene: SceneSpec, mount: mujoco.MjsBody
) -> tuple[list[str], list[str], str, str, list[float]]:
    robot = scene.robot
    assert robot.mjcf is not None and robot.joints and robot.actuators and robot.flange_body
    try:
        child = mujoco.MjSpec.from_file(str(robot.mjcf))
    except ValueError as err:
        raise SpecError(f"robot.mjcf {robot.mjcf} could not be loaded: {err}") from None
    root = child.worldbody.first_body()
    if root is None:
        raise SpecError(f"robot.mjcf {robot.mjcf} has no body under <worldbody>")
    frame = mount.add_frame()
    with _quiet_empty_prefix_warning():
        frame.attach_body(root, "", "")
    names = {
        "joint": (robot.joints, {j.name for j in spec.joints}),
        "actuator": (robot.actuators, {a.name for a in spec.actuators}),
        "body": ([robot.flange_body], {b.name for b in spec.bodies}),
    }
    if robot.tcp_site is not None:
        names["site"] = ([robot.tcp_site], {s.name for s in spec.sites})
    missing = [
        f"{kind} '{n}'" for kind, (want, have) in names.items() for n in want if n not in have
    ]
    if missing:
        raise SpecError(
            f"robot.mjcf {robot.mjcf} lacks {', '.join(missing)}; fix the names in the spec"
        )
    home = list(robot.home_qpos) if robot.home_qpos else [0.0] * len(robot.joints)
    if len(home) != len(robot.joints):
        raise SpecError(f"robot.home_qpos has {len(home)} values for {len(robot.joints)} joints")
    return list(robot.joints), list(robot.actuators), robot.flange_body, robot.tcp_site or "", home


def _euler_quat(euler: tuple[float, float, float] | list[float]) -> list[float]:
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.asarray(euler, float), "xyz")
    return quat.tolist()


def yaw_quat(yaw: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by ``yaw`` about the vertical axis."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def geom_volume(geom: GeomSpec) -> float:
    """Volume (m^3) of a geom, used to turn an object's mass into a density (a mesh
    counts by its convex hull, which is what MuJoCo collides with)."""
    s = geom.size
    match geom.type:
        case "mesh":
            from scipy.spatial import ConvexHull  # here: scipy.spatial takes 0.2 s to load

            return float(ConvexHull(mesh_vertices(geom.file)).volume)
        case "box":
            return 8 * s[0] * s[1] * s[2]
        case "cylinder":
            return np.pi * s[0] ** 2 * 2 * s[1]
        case "capsule":
            return np.pi * s[0] ** 2 * 2 * s[1] + 4 / 3 * np.pi * s[0] ** 3
        case "sphere":
            return 4 / 3 * np.pi * s[0] ** 3
        case "prism":
            area = 0.5 * geom.sides * s[0] ** 2 * np.sin(2 * np.pi / geom.sides)
            return area * 2 * s[1]
    raise AssertionError(geom.type)


def mesh_vertices(path: str | Path) -> np.ndarray:
    """(N, 3) vertices of a mesh file (OBJ, STL, PLY)."""
    import open3d as o3d  # heavy; only scenes with mesh geoms need it

    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(mesh.vertices)
    if len(vertices) < 4:
        raise SpecError(f"{path}: no mesh could be read from this file (OBJ, STL or PLY)")
    return vertices


def prism_vertices(sides: int, radius: float, half_height: float) -> np.ndarray:
    """Vertices of a regular prism with a flat face normal to +x (shape (2*sides, 3))."""
    angles = np.pi / sides + 2 * np.pi * np.arange(sides) / sides
    ring = np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1)
    top = np.hstack([ring, np.full((sides, 1), half_height)])
    bottom = np.hstack([ring, np.full((sides, 1), -half_height)])
    return np.vstack([top, bottom])


_GEOM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "prism": mujoco.mjtGeom.mjGEOM_MESH,
    "mesh": mujoco.mjtGeom.mjGEOM_MESH,
}


def _add_object(spec: mujoco.MjSpec, scene: SceneSpec, obj: ObjectSpec) -> None:
    x, y, z = obj.pos
    body = spec.worldbody.add_body(
        name=obj.name,
        pos=[x, y, scene.table.top_height + z],
        quat=yaw_quat(obj.yaw).tolist(),
    )
    if obj.role == "manipulated":
        body.add_freejoint(name=f"{obj.name}_free")
        volume = sum(geom_volume(g) for g in obj.geoms if g.contact)
        density = obj.mass / volume if obj.mass else 1000.0
    else:
        body.mocap = True
        density = 1000.0
    look = ""
    if obj.look is not None:
        look = f"{obj.name}_look"
        spec.add_texture(name=look, type=mujoco.mjtTexture.mjTEXTURE_2D, file=str(obj.look))
        spec.add_material(name=look).textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = look
    for i, geom in enumerate(obj.geoms):
        kwargs = {}
        size = list(geom.size) + [0.0] * (3 - len(geom.size))
        if geom.type == "prism":
            mesh_name = f"{obj.name}_mesh{i}"
            spec.add_mesh(
                name=mesh_name,
                uservert=prism_vertices(geom.sides, geom.size[0], geom.size[1]).ravel().tolist(),
            )
            kwargs["meshname"] = mesh_name
            size = [0.0, 0.0, 0.0]
        elif geom.type == "mesh":
            mesh_name = f"{obj.name}_mesh{i}"
            spec.add_mesh(name=mesh_name, file=str(geom.file))
            kwargs["meshname"] = mesh_name
            size = [0.0, 0.0, 0.0]
        contact = geom.contact
        if look and not contact:
            kwargs["material"] = look
        body.add_geom(
            name=f"{obj.name}_geom{i}",
            type=_GEOM_TYPES[geom.type],
            size=size,
            pos=list(geom.pos),
            quat=_euler_quat(geom.euler),
            rgba=[1.0, 1.0, 1.0, 1.0] if look and not contact else list(geom.rgba or obj.rgba),
            friction=[obj.friction, 0.01, 0.0001],
            condim=4 if contact else 3,
            density=density if contact else 0.0,
            contype=ENV_CONTYPE if contact else 0,
            conaffinity=ENV_CONAFFINITY if contact else 0,
            group=(UNSEEN_GROUP if look else 0) if contact else VISUAL_GROUP,
            **kwargs,
        )


def look_at_quat(pos: np.ndarray, target: np.ndarray, up: np.ndarray) -> list[float]:
    """Camera quaternion looking from ``pos`` at ``target`` (MuJoCo cameras look along -z)."""
    forward = np.asarray(target, float) - np.asarray(pos, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    rot = np.stack([right, cam_up, -forward], axis=1)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, rot.ravel())
    return quat.tolist()


def _add_camera(spec: mujoco.MjSpec, scene: SceneSpec, cam: CameraSpec, flange: str) -> None:
    if cam.mount == "world":
        parent, up = spec.worldbody, cam.up or (0.0, 0.0, 1.0)
    else:
        parent, up = spec.body(flange), cam.up or (1.0, 0.0, 0.0)
    quat = look_at_quat(np.array(cam.pos), np.array(cam.lookat), np.array(up))
    parent.add_camera(
        name=cam.name,
        pos=list(cam.pos),
        quat=quat,
        fovy=cam.fovy,
        resolution=[cam.width, cam.height],
    )
