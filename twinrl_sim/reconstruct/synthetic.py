"""A rendered stand-in for a phone video of a cell: the test data of ``twinrl twin build``.

The cell of a scene spec (table and objects; the arm is left out, as in a walk-around
clip of the workspace) gets textures a feature matcher can hold on to (multi-scale noise
on the table and the objects) and printed tags (AprilTag 36h11 unless told otherwise)
lying on the table. A hand-held-like camera walks an arc around the table (slow azimuth
sweep, wobbling height, distance and aim) and the frames are written as an mp4 with
PyAV. Ground truth is the scene that rendered it and the camera path
(:class:`Walkthrough`).

That clip is kinder than a real one. :data:`REALISTIC_WALK` films what a user has: a
plain white table, a translucent bottle, textured clutter and a carpet behind, a 50 deg
sweep, motion blur, and a phone's lens, auto exposure, noise and JPEG stills
(:mod:`~twinrl_sim.reconstruct.camera_traits`), written as a folder of frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import av
import cv2
import mujoco
import numpy as np

from twinrl_sim.build import FLOOR_DEPTH, build_mjspec, yaw_quat
from twinrl_sim.reconstruct.camera_traits import (
    REALISTIC_TRAITS,
    CameraTraits,
    TraitApplier,
    pinhole_intrinsics,
)
from twinrl_sim.reconstruct.tag import DEFAULT_FAMILY, family, tag_image
from twinrl_sim.spec import GeomSpec, ObjectSpec, SceneSpec, TableSpec

HIDDEN_GROUP = 5  # geom group of the arm, not rendered
TAG_MARGIN_CELLS = 1  # white cells around the black square


@dataclass(frozen=True)
class TagPlacement:
    """A printed tag lying face up on the table."""

    tag_id: int = 0
    xy: tuple[float, float] = (0.3, 0.3)  # centre, base frame (m)
    yaw: float = 0.3  # rad, printed x from the base's x
    size: float = 0.08  # edge of the black square (m)
    family: str = DEFAULT_FAMILY  # see twinrl_sim.reconstruct.tag.FAMILIES


ONE_TAG = (TagPlacement(),)
# Three tags spread over the pick-and-place table, clear of its objects: the stand-in for
# tags whose centres were touched with the TCP (``--tag-point``).
THREE_TAGS = (
    TagPlacement(),
    TagPlacement(tag_id=1, xy=(0.7, 0.4), yaw=-0.5, size=0.06),
    TagPlacement(tag_id=2, xy=(0.25, -0.45), yaw=0.9, size=0.06),
)


@dataclass(frozen=True)
class WalkthroughSettings:
    """Shape of the clip. Defaults: a short clip for tests (8 s at 10 fps)."""

    seconds: float = 8.0
    fps: float = 10.0
    width: int = 640
    height: int = 480
    sweep_deg: float = 140.0  # azimuth covered by the walk
    distance: float = 1.0  # m from the aim point
    elevation_deg: float = -45.0
    jitter: float = 0.01  # m of hand shake in the aim point
    motion_blur: int = 1  # sub-frames averaged per frame (1: none)
    static: bool = False  # the camera does not move (a bad clip, for tests)
    plain_table: bool = False  # the table top keeps its spec colour, with no texture
    clutter: int = 0  # textured boxes standing behind the table, and a carpet under them
    shiny_table: bool = False  # a glossy plain top (highlights, reflections), lit for shadows
    traits: CameraTraits = field(
        default_factory=CameraTraits
    )  # the phone's lens, exposure, noise, JPEG


REALISTIC_WALK = WalkthroughSettings(
    seconds=9.3,
    sweep_deg=50.0,
    distance=0.9,
    elevation_deg=-35.0,
    jitter=0.02,
    motion_blur=3,
    plain_table=True,
    clutter=8,
    traits=REALISTIC_TRAITS,
)
"""93 frames at 640x480 of the cell a real user films: see the module's docstring."""

LOW_WALK = replace(REALISTIC_WALK, elevation_deg=-22.0, shiny_table=True)
"""The realistic walk filmed low (the phone about 0.34 m over the table), over a glossy
top that shows highlights, reflections and shadows: what stands on the table is seen
mostly against the clutter beyond its far edge."""

OFFICE_SCENE = SceneSpec(
    name="office",
    table=TableSpec(size=(0.8, 1.4), center=(0.5, 0.0), rgba=(0.93, 0.93, 0.91, 1)),
    objects=[
        ObjectSpec(
            name="bottle",
            role="manipulated",
            mass=0.3,
            pos=(0.62, 0.15, 0.125),
            rgba=(0.85, 0.9, 0.95, 0.35),
            geoms=[GeomSpec(type="cylinder", size=[0.0375, 0.125])],
        )
    ],
)
"""What a new user films first: a white office table, a clear drinking bottle (7.5 cm
across, 25 cm tall) and :data:`OFFICE_TAG`, a 14 cm tag, lying beside it."""
OFFICE_TAG = (TagPlacement(tag_id=12, xy=(0.5, 0.0), yaw=0.0, size=0.14),)

CLUTTERED_SCENE = SceneSpec(
    name="cluttered_office",
    table=TableSpec(size=(0.8, 1.4), center=(0.5, 0.0), rgba=(0.93, 0.93, 0.91, 1)),
    objects=[
        ObjectSpec(
            name="bottle",
            role="manipulated",
            mass=0.4,
            pos=(0.33, 0.14, 0.115),
            geoms=[
                GeomSpec(type="cylinder", size=[0.035, 0.115], rgba=(0.12, 0.1, 0.08, 0.85)),
                GeomSpec(
                    type="cylinder",
                    size=[0.0355, 0.04],
                    pos=(0.0, 0.0, -0.035),
                    rgba=(0.9, 0.75, 0.3, 1),
                ),
            ],
        ),
        ObjectSpec(
            name="box",
            role="manipulated",
            mass=0.5,
            pos=(0.42, -0.2, 0.17),
            yaw=0.4,
            rgba=(0.55, 0.2, 0.6, 1),
            geoms=[GeomSpec(type="box", size=[0.05, 0.035, 0.17])],
        ),
    ],
)
"""The cases a real clip failed on, filmed with :data:`LOW_WALK` and :data:`OFFICE_TAG`:
a dark glass bottle (23 cm) wrapped in a printed label, near the table's far edge, and
a box (34 cm) taller than the phone is held over the table for much of the walk."""


@dataclass(frozen=True)
class Walkthrough:
    """What was rendered: the clip and its ground truth."""

    video: Path
    tags: tuple[TagPlacement, ...]
    tag_poses: dict[int, np.ndarray]  # id -> (7,) pose in the base frame: x y z qw qx qy qz
    camera_positions: np.ndarray  # (T, 3) in the base frame
    fovy_deg: float
    intrinsics: tuple[float, ...]  # fx fy cx cy, then k1 k2 p1 p2 when the lens distorts


def _noise_texture(rng: np.random.Generator, size: int, low: float, high: float) -> np.ndarray:
    """Grey multi-scale value noise in [low, high] as (size, size, 3) uint8."""
    field = np.zeros((size, size))
    for cells, weight in ((4, 1.0), (16, 0.6), (64, 0.4), (size, 0.3)):
        coarse = rng.random((cells, cells))
        reps = size // cells
        field += weight * np.kron(coarse, np.ones((reps, reps)))[:size, :size]
    field = (field - field.min()) / np.ptp(field)
    grey = (255 * (low + (high - low) * field)).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def _add_texture(spec: mujoco.MjSpec, name: str, image: np.ndarray, rgba, repeat=(1, 1)) -> str:
    texture = spec.add_texture(
        name=name,
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        width=image.shape[1],
        height=image.shape[0],
        nchannel=3,
    )
    texture.data = np.ascontiguousarray(image).tobytes()
    material = spec.add_material(name=f"{name}_material", rgba=list(rgba), texrepeat=list(repeat))
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    return f"{name}_material"


def walkthrough_model(
    scene: SceneSpec,
    tags: tuple[TagPlacement, ...],
    seed: int,
    image_size: tuple[int, int],
    *,
    plain_table: bool = False,
    clutter: int = 0,
    shiny_table: bool = False,
) -> tuple[mujoco.MjModel, dict[int, np.ndarray]]:
    """The cell with the tags, able to render ``image_size`` (width, height) images, and
    each tag's pose (x y z qw qx qy qz) by id. Opaque objects (and the table unless
    ``plain_table``) get noise textures; a translucent object (alpha below 1) stays
    clear and glossy, as a drinking bottle is. ``clutter`` boxes stand behind the table;
    a ``shiny_table`` has highlights and reflections, and the lights cast shadows."""
    rng = np.random.default_rng(seed)
    spec, _ = build_mjspec(scene, apply_spec_effects=False)
    width, height = image_size
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, width)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, height)
    if not plain_table:
        table = spec.geom("table_top")
        table.material = _add_texture(
            spec, "walk_table", _noise_texture(rng, 1024, 0.35, 1.0), scene.table.rgba
        )
        table.rgba = [0.5, 0.5, 0.5, 1]  # the default: the material's colour applies
    elif shiny_table:
        gloss = spec.add_material(name="walk_gloss", specular=0.8, shininess=0.7)
        gloss.reflectance = 0.15
        spec.geom("table_top").material = gloss.name
        for light in spec.lights:
            light.castshadow = True
    own_bodies = {"world", "table", *scene.object_names}
    for index, geom in enumerate(spec.geoms):
        body = geom.parent.name or "world"
        if body not in own_bodies:
            geom.group = HIDDEN_GROUP
        elif body in scene.object_names and 0 < geom.rgba[3] < 1:
            geom.material = ""
            glossy = spec.add_material(name=f"walk_glossy{index}", specular=0.9, shininess=0.9)
            glossy.reflectance = 0.2
            geom.material = glossy.name
        elif body in scene.object_names and geom.rgba[3] > 0 and not geom.material:
            noise = _noise_texture(rng, 128, 0.6, 1.0)
            geom.material = _add_texture(spec, f"walk_geom{index}", noise, list(geom.rgba))
            geom.rgba = [0.5, 0.5, 0.5, 1]
    if clutter:
        _add_clutter(spec, scene, clutter, rng)
    top = scene.table.top_height
    thickness = 0.0006
    poses = {}
    for tag in tags:
        cells = family(tag.family).cells
        edge = tag.size * (cells + 2 * TAG_MARGIN_CELLS) / cells
        image = tag_image(tag.tag_id, 32, TAG_MARGIN_CELLS, tag.family)
        quat = yaw_quat(tag.yaw)
        spec.worldbody.add_geom(
            name=f"apriltag{tag.tag_id}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[edge / 2, edge / 2, thickness / 2],
            pos=[tag.xy[0], tag.xy[1], top + thickness / 2],
            quat=quat.tolist(),
            material=_add_texture(
                spec, f"walk_tag{tag.tag_id}", np.repeat(image[:, :, None], 3, axis=2), (1, 1, 1, 1)
            ),
            contype=0,
            conaffinity=0,
        )
        poses[tag.tag_id] = np.concatenate([[tag.xy[0], tag.xy[1], top + thickness], quat])
    return spec.compile(), poses


def _add_clutter(
    spec: mujoco.MjSpec, scene: SceneSpec, boxes: int, rng: np.random.Generator
) -> None:
    """A carpet and ``boxes`` textured boxes on the floor beyond the table's base side,
    where a walk on the far side looks past the table: what stands behind a real cell."""
    floor = spec.geom("floor")
    floor.material = _add_texture(
        spec, "walk_carpet", _noise_texture(rng, 512, 0.2, 0.6), (0.55, 0.5, 0.45, 1), (6, 6)
    )
    floor.rgba = [0.5, 0.5, 0.5, 1]
    table = scene.table
    floor_z = table.top_height - FLOOR_DEPTH
    near_edge = table.center[0] - table.size[0] / 2
    for index in range(boxes):
        half = rng.uniform([0.1, 0.1, 0.15], [0.25, 0.3, 0.5])
        x = near_edge - rng.uniform(0.35, 1.2)
        y = table.center[1] + rng.uniform(-1.0, 1.0)
        colour = [*rng.uniform(0.3, 0.9, 3), 1.0]
        spec.worldbody.add_geom(
            name=f"walk_clutter{index}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=half.tolist(),
            pos=[x, y, floor_z + half[2]],
            quat=yaw_quat(rng.uniform(-0.6, 0.6)).tolist(),
            material=_add_texture(
                spec, f"walk_clutter{index}", _noise_texture(rng, 128, 0.4, 1.0), colour
            ),
            contype=0,
            conaffinity=0,
        )


def _camera_path(
    settings: WalkthroughSettings, aim: np.ndarray, rng: np.random.Generator
) -> list[tuple[np.ndarray, float, float, float]]:
    """(look-at point, distance, azimuth, elevation) per frame and blur sub-frame."""
    steps = max(round(settings.seconds * settings.fps), 2) * settings.motion_blur
    motion = 0.0 if settings.static else 1.0
    s = np.linspace(0.0, 1.0, steps) * motion
    start = 180.0 - settings.sweep_deg / 2  # the walk is on the far side from the arm
    phases = rng.uniform(0, 2 * math.pi, 4)  # 4 draws: the stream the test clips use
    drift = np.cumsum(rng.normal(0, 1, (steps, 3)), axis=0)
    drift = drift - np.linspace(0, 1, steps)[:, None] * drift[-1]  # a bridge: no net walk
    drift *= motion * settings.jitter / max(np.abs(drift).max(), 1e-9)
    azimuth = start + settings.sweep_deg * s
    elevation = settings.elevation_deg + motion * 6.0 * np.sin(2 * math.pi * 1.5 * s + phases[0])
    distance = settings.distance + motion * 0.1 * np.sin(2 * math.pi * s + phases[1])
    return list(zip(aim + drift, distance, azimuth, elevation, strict=True))


def render_walkthrough(
    scene: SceneSpec,
    out: str | Path,
    *,
    tags: tuple[TagPlacement, ...] = ONE_TAG,
    settings: WalkthroughSettings = WalkthroughSettings(),
    seed: int = 0,
) -> Walkthrough:
    """Render the hand-held walk around ``scene``'s table to ``out``: an mp4, or a
    folder of numbered JPEG frames when the settings' camera saves JPEGs."""
    rng = np.random.default_rng(seed)
    size = (settings.width, settings.height)
    model, tag_poses = walkthrough_model(
        scene,
        tags,
        seed,
        size,
        plain_table=settings.plain_table,
        clutter=settings.clutter,
        shiny_table=settings.shiny_table,
    )
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    renderer = mujoco.Renderer(model, settings.height, settings.width)
    option = mujoco.MjvOption()
    option.geomgroup[HIDDEN_GROUP] = 0
    camera = mujoco.MjvCamera()
    table = scene.table
    aim = np.array([table.center[0], table.center[1] * 0.5, table.top_height])
    path = _camera_path(settings, aim, rng)
    fovy = float(model.vis.global_.fovy)
    pinhole = pinhole_intrinsics(settings.width, settings.height, fovy)
    traits = settings.traits
    apply_traits = TraitApplier(
        traits,
        pinhole,
        size,
        len(path) // settings.motion_blur,
        np.random.default_rng([seed, 1]),  # its own stream: the path stays as it was
    )
    out = Path(out)
    positions = []
    try:
        with _FrameWriter(out, settings.fps, size, traits.jpeg_quality) as writer:
            for index, start in enumerate(range(0, len(path), settings.motion_blur)):
                frames = []
                for lookat, distance, azimuth, elevation in path[
                    start : start + settings.motion_blur
                ]:
                    camera.lookat[:], camera.distance = lookat, distance
                    camera.azimuth, camera.elevation = azimuth, elevation
                    renderer.update_scene(data, camera, option)
                    frames.append(renderer.render().astype(np.float32))
                eyes = renderer.scene.camera  # a mono render looks from between the eyes
                positions.append((np.array(eyes[0].pos) + np.array(eyes[1].pos)) / 2)
                image = np.mean(frames, axis=0).round().astype(np.uint8)
                writer.write(apply_traits(image, index))
    finally:
        renderer.close()
    intrinsics = pinhole + (traits.distortion if traits.distorted else ())
    return Walkthrough(out, tags, tag_poses, np.array(positions), fovy, intrinsics)


class _FrameWriter:
    """Frames to an mp4 (H.264, near lossless) or, given a JPEG quality, to a folder of
    numbered JPEGs, as a phone's burst or a frame export gives them."""

    def __init__(
        self, out: Path, fps: float, size: tuple[int, int], jpeg_quality: int | None
    ) -> None:
        self.out, self.fps, self.size, self.quality = out, fps, size, jpeg_quality
        self.count = 0

    def __enter__(self) -> _FrameWriter:
        if self.quality is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            return self
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.container = av.open(str(self.out), mode="w")
        self.stream = self.container.add_stream("libx264", rate=round(self.fps))
        self.stream.width, self.stream.height = self.size
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": "18"}
        return self

    def write(self, image: np.ndarray) -> None:
        if self.quality is not None:
            path = self.out / f"frame_{self.count:05d}.jpg"
            bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(path), bgr, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        else:
            for packet in self.stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                self.container.mux(packet)
        self.count += 1

    def __exit__(self, *exc) -> None:
        if self.quality is None:
            for packet in self.stream.encode():
                self.container.mux(packet)
            self.container.close()


def render_fixed_view(
    scene: SceneSpec,
    camera: str,
    out: str | Path,
    *,
    tags: tuple[TagPlacement, ...] = ONE_TAG,
    size: tuple[int, int] = (640, 480),
    seed: int = 0,
) -> Path:
    """A photo (PNG) of the textured cell (arm left out, as in the walk) from
    ``scene``'s camera ``camera``: the stand-in for a frame of a fixed real camera."""
    model, _ = walkthrough_model(scene, tags, seed, size)
    width, height = size
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    option = mujoco.MjvOption()
    option.geomgroup[HIDDEN_GROUP] = 0
    with mujoco.Renderer(model, height, width) as renderer:
        renderer.update_scene(data, camera, option)
        image = renderer.render()
    cv2.imwrite(str(out), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return out
