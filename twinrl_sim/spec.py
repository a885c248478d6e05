"""The scene spec: a versioned, hashable YAML description of a robot cell.

A spec names the robot, the table, the objects (primitive geometry, mass, friction), the
cameras and lights, the physics rates and any identified physical effects. It is plain
data: :func:`twinrl_sim.build.compile_scene` turns it into a MuJoCo model through
``mujoco.MjSpec``. Its :attr:`SceneSpec.digest` is what episodes record as ``twin``.

Example (abridged)::

    version: 1
    name: pick_place
    robot: {builtin: ur5e}
    table: {size: [0.9, 1.2], top_height: 0.0}
    objects:
      - name: banana
        role: manipulated
        mass: 0.12
        geoms: [{type: capsule, size: [0.018, 0.07], euler: [0, 1.5708, 0]}]
    cameras:
      - {name: front, pos: [1.2, 0.0, 0.6], lookat: [0.45, 0.0, 0.0]}
    effects:
      joint_friction: {coulomb: [0.5, 0.5, 0.4, 0.1, 0.1, 0.1]}
"""

from __future__ import annotations

import difflib
import hashlib
import json
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from twinrl_data.atomic import write_text_atomic
from twinrl_sim.effects import validate_effects
from twinrl_sim.errors import TwinError

SCHEMA_VERSION = 1

# Every number is finite and physically bounded: a NaN, an infinity or 1e300 anywhere
# would compile and then simulate to NaN. Positions and sizes are metres within a cell.
Coordinate = Annotated[float, Field(allow_inf_nan=False, ge=-10.0, le=10.0)]
Angle = Annotated[float, Field(allow_inf_nan=False, ge=-100.0, le=100.0)]  # rad
Vec3 = tuple[Coordinate, Coordinate, Coordinate]
Unit = Annotated[float, Field(ge=0, le=1)]
Rgba = tuple[
    Annotated[float, Field(ge=0, le=1)],
    Annotated[float, Field(ge=0, le=1)],
    Annotated[float, Field(ge=0, le=1)],
    Annotated[float, Field(ge=0, le=1)],
]
Positive = Annotated[float, Field(gt=0, le=10.0, allow_inf_nan=False)]  # a size (m)
Mass = Annotated[float, Field(gt=0, le=1000.0, allow_inf_nan=False)]  # kg


class SpecError(TwinError):
    """A scene spec (or an effects file) is invalid; the message says where and why."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class GeomSpec(_Strict):
    """One primitive of an object. Sizes follow MuJoCo: half extents, radius, half length.

    ``prism`` is a regular prism: ``size = [circumradius, half_height]`` with ``sides``
    faces (a hexagonal block is ``sides: 6``). ``mesh`` is a triangle mesh file (OBJ or
    STL, metres, in the object's frame) given by ``file``, relative to the spec's folder;
    MuJoCo collides with its convex hull, so a non-convex object is several convex
    ``mesh`` parts (``twinrl twin build`` writes them) plus, optionally, its whole
    surface as a ``contact: false`` mesh for looks.
    """

    type: Literal["box", "cylinder", "capsule", "sphere", "prism", "mesh"]
    size: list[Positive] = Field(default_factory=list, max_length=3)
    file: Path | None = None
    pos: Vec3 = (0.0, 0.0, 0.0)
    euler: tuple[Angle, Angle, Angle] = (0.0, 0.0, 0.0)
    rgba: Rgba | None = None
    sides: int = Field(default=6, ge=3, le=64)
    contact: bool = True

    @model_validator(mode="after")
    def _check_size(self) -> GeomSpec:
        if self.type == "mesh":
            if self.file is None or self.size:
                raise TwinError("a mesh geom needs 'file' (OBJ or STL) and no 'size'")
            return self
        if self.file is not None:
            raise TwinError(f"'file' is for mesh geoms only, not a {self.type}")
        expected = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1, "prism": 2}[self.type]
        if len(self.size) != expected:
            raise TwinError(f"a {self.type} needs {expected} size value(s), got {len(self.size)}")
        return self


class ObjectSpec(_Strict):
    """A body on the table. ``manipulated`` objects are free; the others are fixed.

    ``pos`` is the body origin: x, y in the base frame and z above the table top.
    """

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    role: Literal["manipulated", "target", "fixture"]
    pos: Vec3 = (0.5, 0.0, 0.0)
    yaw: Angle = 0.0
    mass: Mass | None = None
    friction: Annotated[float, Field(gt=0, le=5)] = 1.0
    rgba: Rgba = (0.8, 0.8, 0.8, 1.0)
    geoms: list[GeomSpec] = Field(min_length=1)
    look: Path | None = None
    """A picture (PNG) wrapped on the object's ``contact: false`` meshes by their OBJ
    texture coordinates (``twinrl twin build`` projects it from the frames); its contact
    parts then collide unseen."""

    @model_validator(mode="after")
    def _mass_for_free_bodies(self) -> ObjectSpec:
        if self.role == "manipulated" and self.mass is None:
            raise TwinError(f"manipulated object '{self.name}' needs a mass (kg)")
        return self

    @model_validator(mode="after")
    def _look_needs_a_surface(self) -> ObjectSpec:
        if self.look is not None and not any(
            g.type == "mesh" and not g.contact for g in self.geoms
        ):
            raise TwinError(
                f"object '{self.name}' has a look but no 'contact: false' mesh to wrap it on"
            )
        return self


class RobotSpec(_Strict):
    """The arm: the built-in UR5e, or any MJCF with its joint, actuator and site names.

    A custom MJCF must have one position actuator per arm joint (named in ``actuators``,
    in joint order) and a site at the tool centre point (``tcp_site``); the built-in
    parallel-jaw gripper is attached to ``flange_body`` unless ``gripper: none``.
    """

    builtin: Literal["ur5e"] | None = "ur5e"
    mjcf: Path | None = None
    joints: list[str] | None = None
    actuators: list[str] | None = None
    flange_body: str | None = None
    tcp_site: str | None = None
    gripper: Literal["parallel_jaw", "none"] = "parallel_jaw"
    base_pos: Vec3 = (0.0, 0.0, 0.0)
    home_qpos: list[Angle] | None = None

    @model_validator(mode="after")
    def _one_source(self) -> RobotSpec:
        if self.mjcf is not None:
            missing = [
                k for k in ("joints", "actuators", "flange_body") if getattr(self, k) is None
            ]
            if missing:
                raise TwinError(
                    f"a custom robot mjcf needs {', '.join(missing)} (names in that file)"
                )
            if self.actuators is not None and len(self.actuators) != len(self.joints or []):
                raise TwinError("robot.actuators must name one actuator per joint, in order")
            if self.gripper == "none" and self.tcp_site is None:
                raise TwinError("a custom robot without the built-in gripper needs tcp_site")
        elif self.builtin is None:
            raise TwinError("robot needs either 'builtin: ur5e' or 'mjcf: PATH'")
        return self

    @property
    def is_builtin(self) -> bool:
        return self.mjcf is None


class TableSpec(_Strict):
    """The table top: ``size`` along its own axes, turned by ``yaw`` about the vertical."""

    size: tuple[Positive, Positive] = (0.9, 1.3)
    center: tuple[Coordinate, Coordinate] = (0.45, 0.0)
    yaw: Angle = 0.0
    thickness: Positive = 0.04
    top_height: Annotated[float, Field(ge=-1.0, le=1.5)] = 0.0
    friction: Annotated[float, Field(gt=0, le=5)] = 0.8
    rgba: Rgba = (0.55, 0.45, 0.35, 1.0)
    texture: Literal["plain", "checker", "gradient"] = "plain"
    image: Path | None = None
    """A picture (PNG) of the top, stretched over it instead of ``texture``: its columns
    run along the table's x (``size[0]``), its first row is the +y edge."""


class CameraSpec(_Strict):
    """A camera. ``mount: world`` cameras look from ``pos`` at ``lookat``; ``wrist``
    cameras are fixed to the flange, ``pos`` in the flange frame, looking along the tool.
    ``up`` is the direction the top of the image leans towards (default: +z for world
    cameras, the flange's +x for wrist cameras); a rolled camera gives its own."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    mount: Literal["world", "wrist"] = "world"
    pos: Vec3
    lookat: Vec3 = (0.45, 0.0, 0.0)
    up: Vec3 | None = None
    fovy: Annotated[float, Field(gt=1, lt=179)] = 60.0
    width: int = Field(default=128, ge=16, le=4096)
    height: int = Field(default=128, ge=16, le=4096)


DEFAULT_CAMERAS = (
    CameraSpec(name="front", pos=(1.35, 0.0, 0.95), lookat=(0.3, 0.0, 0.05), fovy=55.0),
    CameraSpec(
        name="wrist", mount="wrist", pos=(-0.075, 0.0, 0.03), lookat=(0.0, 0.0, 0.2), fovy=75.0
    ),
)


class LightSpec(_Strict):
    pos: Vec3 = (0.4, 0.0, 1.5)
    dir: Vec3 = (0.0, 0.0, -1.0)
    diffuse: tuple[Unit, Unit, Unit] = (0.7, 0.7, 0.7)


class WorkspaceSpec(_Strict):
    """Box (base frame, metres) that the tool centre point is clamped to."""

    low: Vec3 = (0.15, -0.55, 0.005)
    high: Vec3 = (0.85, 0.55, 0.6)

    @model_validator(mode="after")
    def _ordered(self) -> WorkspaceSpec:
        if any(lo >= hi for lo, hi in zip(self.low, self.high, strict=True)):
            raise TwinError(f"workspace.low {self.low} must be below workspace.high {self.high}")
        return self


class PhysicsSpec(_Strict):
    timestep: Annotated[float, Field(ge=1e-5, le=0.01)] = 0.002
    control_hz: Annotated[float, Field(ge=0.1, le=1000)] = 10.0
    # How the arm's servos follow targets (twinrl_sim.servo): "hold" each for its period,
    # or "track" them as a UR's servoJ does, leading by servo_lead seconds of speed
    # (None: the lead that cancels the servos' lag).
    servo: Literal["hold", "track"] = "hold"
    servo_lead: Annotated[float, Field(ge=-0.2, le=0.5)] | None = None
    # What the servos feed forward (twinrl_sim.servo): "model" (the weight of all the arm
    # carries, logged in its joint torques as a UR's target_moment) or "none" (None:
    # "model" where the servos track, "none" where they hold).
    feedforward: Literal["model", "none"] | None = None

    @model_validator(mode="after")
    def _whole_substeps(self) -> PhysicsSpec:
        ratio = 1.0 / (self.control_hz * self.timestep)
        if abs(ratio - round(ratio)) > 1e-6:
            raise TwinError(
                f"control period 1/{self.control_hz} s is not a whole number of "
                f"{self.timestep} s physics steps"
            )
        return self

    @property
    def feeds_forward(self) -> bool:
        """Whether the servos feed forward the arm's model (see ``feedforward``)."""
        if self.feedforward is None:
            return self.servo == "track"
        return self.feedforward == "model"

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return round(1.0 / (self.control_hz * self.timestep))


class SceneSpec(_Strict):
    """A whole cell. Load with :func:`load_spec`, compile with ``compile_scene``."""

    version: Literal[1] = SCHEMA_VERSION
    name: str
    robot: RobotSpec = RobotSpec()
    table: TableSpec = TableSpec()
    objects: list[ObjectSpec] = []
    cameras: list[CameraSpec] = Field(default_factory=lambda: list(DEFAULT_CAMERAS))
    lights: list[LightSpec] = [LightSpec()]
    workspace: WorkspaceSpec = WorkspaceSpec()
    physics: PhysicsSpec = PhysicsSpec()
    effects: dict[str, dict[str, Any]] = {}
    backdrop: Path | None = None
    """The room behind the cell seen at infinity (PNG, six square faces stacked: +x, -x,
    +y, -y, +z, -z of the base frame, each as seen from inside, OpenGL's cube-map
    orientation); default a plain gradient."""
    provenance: dict[str, Any] = {}

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, value: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        validate_effects(value)
        return value

    @model_validator(mode="after")
    def _unique_names(self) -> SceneSpec:
        for kind, names in (
            ("object", [o.name for o in self.objects]),
            ("camera", [c.name for c in self.cameras]),
        ):
            dupes = sorted({n for n in names if names.count(n) > 1})
            if dupes:
                raise TwinError(f"duplicate {kind} name(s): {', '.join(dupes)}")
        return self

    def object(self, name: str) -> ObjectSpec:
        """The object called ``name``; a ``KeyError`` names the ones that exist."""
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise SpecError(f"no object '{name}' in scene '{self.name}' (has: {self.object_names})")

    @property
    def object_names(self) -> list[str]:
        return [o.name for o in self.objects]

    @property
    def digest(self) -> str:
        """Short content hash: same spec (and same robot file) gives the same digest.

        ``provenance`` is excluded: it documents where a spec came from, not what it is.
        """
        payload = self.model_dump(mode="json", exclude={"provenance"})
        # Files count by content, not by where they lie.
        if self.robot.mjcf is not None:
            payload["robot"]["mjcf"] = _file_sha256(self.robot.mjcf)
        for obj in payload["objects"]:
            for geom in obj["geoms"]:
                if geom["file"] is not None:
                    geom["file"] = _file_sha256(geom["file"])
            if obj["look"] is not None:
                obj["look"] = _file_sha256(obj["look"])
        for owner, key in ((payload["table"], "image"), (payload, "backdrop")):
            if owner[key] is not None:
                owner[key] = _file_sha256(owner[key])
        text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def with_effects(self, effects: dict[str, dict[str, Any]]) -> SceneSpec:
        """A copy with ``effects`` merged over this spec's own (validated)."""
        return parse_spec(
            {**self.model_dump(mode="python"), "effects": {**self.effects, **effects}}
        )

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json", exclude_defaults=False), sort_keys=False)


def validate_model[Model: BaseModel](
    model: type[Model], data: object, source: str, error: type[Exception]
) -> Model:
    """Validate a mapping as ``model``; raise ``error`` naming every problem in one line,
    unknown keys with the nearest valid one (scene specs, cell files)."""
    if not isinstance(data, dict):
        raise error(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise error(f"{source}: {format_validation_error(err, model)}") from None


def read_yaml(path: Path, what: str, error: type[Exception], hint: str = "") -> object:
    """The YAML document of ``path`` (a ``what``: scene spec, cell file), or ``error`` in
    one line when it is a folder, missing or not YAML."""
    if path.is_dir():
        raise error(f"{path} is a folder; give a {what} (YAML)")
    if not path.is_file():
        raise error(f"{what} {path} does not exist{hint}")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise error(f"{path}: not valid YAML ({err.__class__.__name__}: {err})") from None


def parse_spec(data: dict[str, Any], source: str = "scene spec") -> SceneSpec:
    """Validate a mapping as a :class:`SceneSpec`; raise :class:`SpecError` on any problem.

    All problems are reported in one message, each with its location and, for unknown
    keys, the nearest valid key.
    """
    return validate_model(SceneSpec, data, source, SpecError)


def load_spec(path: str | Path) -> SceneSpec:
    """Read and validate a scene spec YAML file."""
    path = Path(path)
    return spec_from_yaml(read_yaml(path, "scene spec", SpecError, SPEC_HINT), path)


SPEC_HINT = "; give a YAML file or a task name"  # said when a scene spec file is missing


def spec_from_yaml(data: object, path: Path) -> SceneSpec:
    """The scene spec of the YAML document ``data`` read from ``path`` (its relative
    file paths resolved from the file's folder)."""
    return resolve_files(parse_spec(data or {}, source=str(path)), path.parent)


def resolve_files(spec: SceneSpec, folder: Path) -> SceneSpec:
    """``spec`` with its relative file paths (robot MJCF, meshes, pictures) made absolute from
    ``folder``; a missing file is a :class:`SpecError` naming it."""
    updates: dict[str, Any] = {}
    if spec.robot.mjcf is not None:
        updates["robot"] = spec.robot.model_copy(
            update={"mjcf": _existing(folder, spec.robot.mjcf, "robot.mjcf")}
        )
    objects = []
    for obj in spec.objects:
        geoms = [
            g.model_copy(
                update={"file": _existing(folder, g.file, f"objects.{obj.name}.geoms.{i}.file")}
            )
            if g.file is not None
            else g
            for i, g in enumerate(obj.geoms)
        ]
        look = obj.look and _existing(folder, obj.look, f"objects.{obj.name}.look")
        objects.append(obj.model_copy(update={"geoms": geoms, "look": look}))
    updates["objects"] = objects
    if spec.table.image is not None:
        image = _existing(folder, spec.table.image, "table.image")
        updates["table"] = spec.table.model_copy(update={"image": image})
    if spec.backdrop is not None:
        updates["backdrop"] = _existing(folder, spec.backdrop, "backdrop")
    return spec.model_copy(update=updates)


def _existing(folder: Path, file: Path, where: str) -> Path:
    path = file if file.is_absolute() else (folder / file).resolve()
    if not path.is_file():
        raise SpecError(f"{where}: {path} does not exist (relative paths start at {folder})")
    return path


def _file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save_spec(spec: SceneSpec, path: str | Path) -> Path:
    """Write ``spec`` as YAML; refuses to overwrite an existing file."""
    path = Path(path)
    if path.exists():
        raise SpecError(f"{path} already exists; choose another path or delete it first")
    write_text_atomic(path, spec.to_yaml())
    return path


def format_validation_error(err: ValidationError, root: type[BaseModel] | None = None) -> str:
    """One line listing every problem pydantic found, with nearest-key suggestions
    (keys looked up from ``root``, the validated model; default :class:`SceneSpec`)."""
    problems = []
    for item in err.errors():
        loc = ".".join(str(p) for p in item["loc"]) or "(top level)"
        if item["type"] == "extra_forbidden":
            key = str(item["loc"][-1])
            parent_model = _model_at(root or SceneSpec, item["loc"][:-1])
            hint = ""
            if parent_model is not None:
                close = difflib.get_close_matches(key, list(parent_model.model_fields), n=1)
                if close:
                    hint = f" (did you mean '{close[0]}'?)"
            problems.append(f"unknown key '{loc}'{hint}")
        else:
            msg = item["msg"].removeprefix("Value error, ")
            problems.append(f"{loc}: {msg} (got {item.get('input')!r})")
    return "; ".join(problems)


def _model_at(model: type[BaseModel], loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The pydantic model class found by walking ``loc`` from ``model``."""
    current: Any = model
    for part in loc:
        if isinstance(part, int):
            continue
        if not (isinstance(current, type) and issubclass(current, BaseModel)):
            return None
        field = current.model_fields.get(str(part))
        if field is None:
            return None
        current = field.annotation
        while typing.get_origin(current) is not None:
            args = [a for a in typing.get_args(current) if isinstance(a, type)]
            models = [a for a in args if issubclass(a, BaseModel)]
            current = models[0] if models else (args[0] if args else None)
            if current is None:
                return None
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None
