"""``twinrl twin build``: from a walk-around clip to a scene spec the rest of twinrl uses.

Stages: frames, structure from motion (with the fixed cameras' photos), metric alignment
to the robot base (tags), table, objects (points and silhouettes, convex parts, names),
cameras, then the scene spec (YAML + mesh assets), which is compiled in MuJoCo before
anything is reported, and the report (Markdown + plots) and the Rerun recording.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import mujoco
import numpy as np
import open3d as o3d

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_sim.build import compile_scene
from twinrl_sim.errors import TwinError
from twinrl_sim.reconstruct.align import (
    Alignment,
    Similarity,
    align_to_points,
    align_to_tag,
    check_reference_points,
)
from twinrl_sim.reconstruct.calibration import FilmingCamera, filming_camera
from twinrl_sim.reconstruct.candidates import judge_candidates
from twinrl_sim.reconstruct.evidence import ObjectEvidence, bound_one_sided, weigh_evidence
from twinrl_sim.reconstruct.frames import CaptureError, select_frames
from twinrl_sim.reconstruct.look import Lighting, frame_views, paint_cell, split_views
from twinrl_sim.reconstruct.look_score import score_look, twin_lighting
from twinrl_sim.reconstruct.objects import (
    DEFAULT_DENSITY,
    TwinObject,
    fit_mesh,
    heading,
    match_task_objects,
    read_mesh,
    reconstruct_shape,
)
from twinrl_sim.reconstruct.report import plot_build, write_build_report, write_build_rrd
from twinrl_sim.reconstruct.result import TwinBuild
from twinrl_sim.reconstruct.segment import (
    PLANE_TOLERANCE,
    ObjectCluster,
    TablePlane,
    TagPlane,
    describe_cluster,
    find_objects,
    level_table,
)
from twinrl_sim.reconstruct.settings import BuildSettings
from twinrl_sim.reconstruct.sfm import MATCHINGS, SparseModel, run_sfm
from twinrl_sim.reconstruct.silhouette import Hull, carve_hulls, join_parts
from twinrl_sim.reconstruct.table_extent import measure_table
from twinrl_sim.reconstruct.tag import FAMILIES
from twinrl_sim.spec import (
    CameraSpec,
    GeomSpec,
    ObjectSpec,
    SceneSpec,
    load_spec,
    parse_spec,
    resolve_files,
)
from twinrl_sim.tasks import make_task

CAMERA_DISTANCE = (0.15, 4.0)  # m: where a hand-held phone can be, seen from the tag
MIN_WORKSPACE_POINTS = 200  # points inside the workspace box needed to find a table in


def check_settings(settings: BuildSettings, out: Path) -> None:
    """Refuse bad arguments before any work is done (one line each)."""
    if settings.tag_pose is not None and settings.tag_points:
        raise TwinError("give either `tag_pose` (one tag) or `tag_points` (3+ tags), not both")
    if settings.tag_points:
        check_reference_points(settings.tag_points)
    elif settings.tag_pose is None:
        raise TwinError(
            "tie the cell to the robot base: give `tag_size` and `tag_pose` of one tag, or "
            "`tag_points` (ID=x,y,z) for 3+ tags"
        )
    else:
        if settings.tag_size is None:
            raise SettingError("tag_pose", "needs `tag_size`, the edge of the tag's black square")
        if len(settings.tag_pose) != 7:
            raise SettingError(
                "tag_pose", f"needs 7 numbers 'x y z qw qx qy qz', got {len(settings.tag_pose)}"
            )
        if np.linalg.norm(settings.tag_pose[3:]) < 1e-6:
            raise SettingError("tag_pose", "has a zero quaternion; a tag lying flat is '1 0 0 0'")
    if settings.tag_family not in FAMILIES:
        raise SettingError(
            "tag_family", f"'{settings.tag_family}' is not one of {', '.join(FAMILIES)}"
        )
    if settings.intrinsics is not None:
        known = settings.intrinsics
        if len(known) not in (4, 8):
            raise SettingError(
                "intrinsics",
                f"needs 4 numbers 'fx fy cx cy' or 8 with 'k1 k2 p1 p2', got {len(known)}",
            )
        if not all(np.isfinite(known)) or min(known[:4]) <= 0:
            raise SettingError(
                "intrinsics", "fx fy cx cy must be positive pixel values (e.g. '600 600 320 240')"
            )
    if settings.intrinsics is not None and settings.calibration is not None:
        raise TwinError("give the camera's `intrinsics` or its `calibration` file, not both")
    if settings.refine_distortion and settings.intrinsics is None and settings.calibration is None:
        raise SettingError(
            "refine_distortion",
            "refines the lens of known intrinsics; give `intrinsics` or a `calibration` "
            "(without them the whole lens is estimated anyway)",
        )
    if settings.calibration is not None and not Path(settings.calibration).is_file():
        raise SettingError("calibration", f"{settings.calibration} is not a file")
    if settings.workspace is not None:
        box = settings.workspace
        if len(box) != 6 or not all(np.isfinite(box)):
            raise SettingError(
                "workspace", f"needs 6 numbers 'x_min y_min z_min x_max y_max z_max', got {box}"
            )
        if any(lo >= hi for lo, hi in zip(box[:3], box[3:], strict=True)):
            raise SettingError("workspace", "each minimum must be below its maximum")
    if settings.matching not in MATCHINGS:
        raise SettingError(
            "matching", f"'{settings.matching}' is not one of {', '.join(MATCHINGS)}"
        )
    if settings.frames < 12:
        raise SettingError("frames", f"must be at least 12, got {settings.frames}")
    if settings.tag_size is not None and not 0.005 <= settings.tag_size <= 1.0:
        raise SettingError(
            "tag_size", f"{settings.tag_size:g} is not a tag edge in metres (an 8 cm tag is 0.08)"
        )
    if out.exists() and any(out.iterdir()):
        raise TwinError(f"{out} exists and is not empty; choose another output folder")
    for what, files in (
        ("object_meshes", settings.object_meshes),
        ("camera_images", settings.camera_images),
    ):
        for name, path in files.items():
            if not Path(path).is_file():
                raise SettingError(what, f"{name}={path}: no such file")
    for name, density in settings.densities.items():
        if not 10 <= density <= 25000:
            raise SettingError("densities", f"{name}={density:g} is not a density in kg/m^3")
    task_scene = make_task(settings.task).scene if settings.task is not None else None
    for camera in _base_cameras(task_scene):
        if camera.name in settings.camera_images and camera.mount != "world":
            raise SettingError(
                "camera_images",
                f"{camera.name}: that camera is on the {camera.mount}; only "
                "fixed cameras can be placed from a photo",
            )
    if task_scene is not None:
        for name in settings.object_meshes:
            if name not in task_scene.object_names:
                raise SettingError(
                    "object_meshes",
                    f"{name}: task '{settings.task}' has no object '{name}' "
                    f"(has: {', '.join(task_scene.object_names)})",
                )


def _base_cameras(task_scene: SceneSpec | None) -> list[CameraSpec]:
    return list(task_scene.cameras if task_scene else SceneSpec(name="cell").cameras)


def build_twin(
    source: str | Path,
    out: str | Path,
    settings: BuildSettings,
    on_stage: Callable[[str], None] | None = None,
) -> TwinBuild:
    """Reconstruct the cell filmed in ``source`` (video or image folder) into ``out``."""
    source, out = Path(source), Path(out)
    check_settings(settings, out)
    task_scene = make_task(settings.task).scene if settings.task else None
    # Read now: a mesh that cannot be used is refused before the work.
    meshes = {name: read_mesh(Path(path)) for name, path in settings.object_meshes.items()}
    work = out / "work"
    seconds: dict[str, float] = {}
    running: list = [None, time.perf_counter()]  # the stage under way and its start

    def stage(name: str | None) -> None:
        now = time.perf_counter()
        if running[0] is not None:
            seconds[running[0]] = now - running[1]
        running[:] = [name, now]
        if name is not None and on_stage is not None:
            on_stage(name)

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        stage("frames")
        selection = select_frames(source, work / "frames", target=settings.frames)
        stage("structure from motion")
        camera = filming_camera(
            source, selection.paths[0], settings.intrinsics, settings.calibration
        )
        model = run_sfm(
            work / "frames",
            work / "sfm",
            fixed_cameras=settings.camera_images,
            seed=settings.seed,
            intrinsics=camera.intrinsics,
            refine_distortion=settings.refine_distortion,
            focal_prior=camera.focal_prior,
            matching=settings.matching,
        )
        stage("alignment")
        if settings.tag_points:
            alignment = align_to_points(
                model, work / "frames", settings.tag_points, settings.tag_family
            )
        else:
            alignment = align_to_tag(
                model,
                work / "frames",
                np.asarray(settings.tag_pose, float),
                settings.tag_size,
                settings.tag_id,
                settings.tag_family,
            )
        pivot = alignment.pivot
        walk = model.walk_images()
        path = alignment.to_base.apply(np.array([i.projection_center() for i in walk]))
        _check_scale(path, pivot, settings)
        stage("table")
        points, colours = alignment.to_base.apply(model.points), model.colors
        if settings.workspace is not None:  # the background is cut before any fitting
            points, colours = _inside(points, colours, settings.workspace)
        table, levelling, levelled = level_table(
            points,
            colours,
            pivot,
            settings.seed,
            tags=tag_plane(settings) if settings.tags_on_table else None,
        )
        to_cell = alignment.to_base.turned(levelling, pivot)  # SfM -> levelled base frame
        on_plane = np.abs(levelled[:, 2] - table.height) < PLANE_TOLERANCE
        table = measure_table(
            table,
            levelled[on_plane, :2],
            model,
            work / "frames",
            to_cell.invert,
            tags=alignment.tag_outlines if settings.tags_on_table else (),
        )
        camera_path = (path - pivot) @ levelling.T + pivot
        stage("objects")
        clusters = find_objects(levelled, colours, table)
        hulls = carve_hulls(
            clusters, table, model, work / "frames", to_cell.invert, to_cell.apply, settings.seed
        )
        clusters, hulls = join_parts(clusters, hulls, table)
        # The tags lying on the table, levelled with it: their sheets are no objects.
        on_table = alignment.tag_outlines if settings.tags_on_table else ()
        tags = [(c - pivot) @ levelling.T + pivot for c in on_table]
        chosen, dropped = judge_candidates(clusters, hulls, table, tags)
        hulls = [hulls[k] for k in chosen]
        clusters = [
            _with_hull(clusters[k], hull, table) for k, hull in zip(chosen, hulls, strict=True)
        ]
        evidence = [weigh_evidence(cluster, model, to_cell) for cluster in clusters]
        clusters = [
            bound_one_sided(c, e, h, table)
            for c, e, h in zip(clusters, evidence, hulls, strict=True)
        ]
        objects, ratio = _objects(clusters, evidence, table, task_scene, meshes, settings)
        stage("cameras")
        cameras = {
            name: _placed_camera(name, model, to_cell, table) for name in settings.camera_images
        }
        stage("look")
        _write_meshes(objects, out)
        scene_of = partial(
            _scene_spec, settings, source, table, objects, cameras, task_scene, model, alignment
        )
        look, judges, pictures, lighting = None, [], {}, {}
        if settings.look:
            painters, judges = split_views(frame_views(model, work / "frames", to_cell))
            look = paint_cell(painters, judges, table, objects)
            plain = resolve_files(scene_of(camera), out)
            look.relight(twin_lighting(plain, painters, dressed=True))
            lighting = twin_lighting(plain, painters, dressed=False)  # of the plain colours
            pictures = look.write(out)
        stage("scene")
        scene_path = out / "scene.yaml"
        write_text_atomic(scene_path, scene_of(camera, pictures, lighting).to_yaml())
        built = TwinBuild(
            scene_path=scene_path,
            scene=load_spec(scene_path),
            selection=selection,
            model=model,
            alignment=alignment,
            table=table,
            objects=objects,
            cameras=cameras,
            levelled=levelled,
            camera_path=camera_path,
            seconds=seconds,
            size_ratio=ratio,
            look=look,
            dropped=dropped,
        )
        compiled = compile_scene(built.scene)  # a SpecError here names what does not compile
        stage("report")
        if judges:
            built.look_score = score_look(built.scene, judges)
        write_build_rrd(built, compiled, out / "reconstruction.rrd")
        plots = plot_build(built, out)
        stage(None)
        write_build_report(built, out, plots)
    except BaseException:  # nothing half-built is left behind
        for part in [out] if created else list(out.iterdir()):
            if part.is_dir():
                shutil.rmtree(part, ignore_errors=True)
            else:
                part.unlink()
        raise
    if not settings.keep_work:
        shutil.rmtree(work, ignore_errors=True)
    return built


def _with_hull(cluster: ObjectCluster, hull: Hull | None, table: TablePlane) -> ObjectCluster:
    """``cluster`` described again with what its silhouettes say: without its points
    outside a hull told by chroma (strays), with the hull's footprint where it outlines
    the object, and its top where that can be trusted."""
    if hull is None:
        return cluster
    inside = hull.holds(cluster.points[:, :2])
    if not hull.chromatic or inside.mean() < 0.5:  # a hull that misses its points says little
        inside[:] = True
    colours = cluster.point_colors
    return describe_cluster(
        cluster.points[inside],
        cluster.color,
        table,
        hull.footprint if hull.outlines else None,
        cluster.outline,
        point_colors=None if colours is None else colours[inside],
        hull_top=hull.trusted_top,
        # A top seen only from above (not trusted) was still seen; no end at all was not.
        top_seen=hull.top_seen if hull.trusted_top is not None else hull.top is not None,
    )


def _inside(
    points: np.ndarray, colours: np.ndarray, workspace: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """The cloud's points (base frame) inside the box ``workspace`` and their colours."""
    low, high = np.asarray(workspace[:3]), np.asarray(workspace[3:])
    keep = np.all((points >= low) & (points <= high), axis=1)
    if keep.sum() < MIN_WORKSPACE_POINTS:
        raise CaptureError(
            f"only {keep.sum()} of {len(points)} points lie inside `workspace` "
            f"{' '.join(f'{v:g}' for v in workspace)}; give the box around the table in "
            "the robot-base frame (m), as 'x_min y_min z_min x_max y_max z_max'"
        )
    return points[keep], colours[keep]


def tag_plane(settings: BuildSettings) -> TagPlane:
    """The plane the tags lie on, in the base frame: the tag's own (``tag_pose``) or the
    one through the tags' centres (``tag_points``)."""
    if settings.tag_pose is not None:
        quat = np.asarray(settings.tag_pose[3:], float)
        normal = np.zeros(3)
        mujoco.mju_rotVecQuat(normal, np.array([0.0, 0.0, 1.0]), quat / np.linalg.norm(quat))
        return TagPlane(np.asarray(settings.tag_pose[:3], float), normal)
    centres = np.array([p[:3] for p in settings.tag_points.values()], float)  # 3+, checked
    centre = centres.mean(axis=0)
    normal = np.linalg.svd(centres - centre)[2][-1]
    return TagPlane(centre, normal if normal[2] >= 0 else -normal)


def _check_scale(camera_path: np.ndarray, pivot: np.ndarray, settings: BuildSettings) -> None:
    """A wrong tag size (or tag centres in the wrong unit) scales the whole cell: the
    phone ends up impossibly near or far."""
    distance = float(np.median(np.linalg.norm(camera_path - pivot, axis=1)))
    low, high = CAMERA_DISTANCE
    if low <= distance <= high:
        return
    if settings.tag_points:
        raise CaptureError(
            f"with these `tag_points` centres the phone was {distance:.2f} m from the tags, "
            f"outside {low:g}-{high:g} m; give the centres in metres in the robot-base frame"
        )
    raise CaptureError(
        f"with `tag_size` {settings.tag_size:g} m the phone was {distance:.2f} m from the "
        f"tag, outside {low:g}-{high:g} m; `tag_size` must be the edge of the tag's black "
        "square in metres"
    )


def _objects(
    clusters: list,
    evidence: list[ObjectEvidence],
    table: TablePlane,
    task_scene: SceneSpec | None,
    meshes: dict[str, o3d.geometry.TriangleMesh],
    settings: BuildSettings,
) -> tuple[list[TwinObject], float | None]:
    if not clusters:
        raise CaptureError(
            "no objects stand out on the table; film them from closer and from several "
            "sides, or on a table of a different colour"
        )
    ratio = None
    if task_scene is not None:
        names, ratio = match_task_objects(clusters, task_scene)
    else:
        names = {}
    taken = set(task_scene.object_names) if task_scene else set()
    spare = (f"object_{k}" for k in range(1, 2 * len(clusters) + 1))
    objects = []
    for index, cluster in enumerate(clusters):
        if index in names:
            name, role = names[index], task_scene.object(names[index]).role
        else:  # not one of the task's objects: an obstacle it must live with
            name = next(n for n in spare if n not in taken)
            role = "fixture" if task_scene is not None else "manipulated"
        if name in meshes:
            position, yaw, shape, rms = fit_mesh(meshes[name], cluster, table.height, settings.seed)
            source, fit_rms = str(settings.object_meshes[name]), rms
        else:
            yaw = heading(cluster)
            shape = reconstruct_shape(cluster, yaw, table.height, settings.seed)
            hulled = cluster.carved is not None or cluster.top_from == "silhouettes"
            source = "points + silhouettes" if hulled else "points"
            position, fit_rms = cluster.center[:2], None
        density = settings.densities.get(name, DEFAULT_DENSITY)
        objects.append(
            TwinObject(
                name=name,
                role=role,
                position=np.asarray(position, float),
                yaw=yaw,
                shape=shape,
                mass=density * shape.volume,
                color=cluster.color,
                cluster=cluster,
                source=source,
                evidence=evidence[index],
                fit_rms=fit_rms,
            )
        )
    unmatched = set(meshes) - {o.name for o in objects}
    if unmatched:
        raise CaptureError(
            f"`object_meshes` names {', '.join(sorted(unmatched))}, which no object on the "
            "table became; with a `task`, name the task's objects"
        )
    return objects, ratio


def _placed_camera(
    name: str,
    model: SparseModel,
    to_cell: Similarity,
    table: TablePlane,
) -> CameraSpec:
    """A world camera at the registered pose and focal length of camera ``name``'s photo
    (``to_cell``: SfM frame to the levelled base frame)."""
    image = model.fixed_image(name)
    camera = model.reconstruction.cameras[image.camera_id]
    centre = to_cell.apply(image.projection_center()[None])[0]
    rotation = image.cam_from_world().rotation.matrix()  # rows: camera x, y, z in SfM frame
    forward = rotation[2] @ to_cell.rotation.T
    up = -rotation[1] @ to_cell.rotation.T
    # Look at where the optical axis meets the table (1 m ahead if it never does).
    reach = (table.height - centre[2]) / forward[2] if forward[2] < -1e-3 else 1.0
    fovy = float(np.degrees(2 * np.arctan(camera.height / (2 * camera.focal_length_y))))
    return CameraSpec(
        name=name,
        pos=tuple(float(v) for v in centre),
        lookat=tuple(float(v) for v in centre + forward * min(reach, 5.0)),
        up=tuple(float(v) for v in up),
        fovy=fovy,
        width=int(camera.width),
        height=int(camera.height),
    )


def _scene_spec(
    settings: BuildSettings,
    source: Path,
    table: TablePlane,
    objects: list[TwinObject],
    cameras: dict[str, CameraSpec],
    task_scene: SceneSpec | None,
    model: SparseModel,
    alignment: Alignment,
    camera: FilmingCamera,
    pictures: dict[str, Path] | None = None,
    lighting: dict[str, Lighting] | None = None,
) -> SceneSpec:
    """The scene spec; ``pictures`` (from :meth:`CellLook.write`) dress it where given,
    and its colours are those the twin's ``lighting`` renders as the frames show them."""
    pictures, lighting = pictures or {}, lighting or {}

    def colour(seen: np.ndarray, owner: str) -> tuple[float, ...]:
        rgb = lighting[owner].colour_for(seen) if owner in lighting else seen
        return (*(float(c) for c in rgb), 1.0)

    base = task_scene.model_dump(mode="python") if task_scene else {"name": "cell"}
    base_cameras = _base_cameras(task_scene)
    merged = [cameras.get(c.name, c) for c in base_cameras]
    merged += [c for n, c in cameras.items() if n not in {m.name for m in merged}]
    frictions = {o.name: o.friction for o in task_scene.objects} if task_scene else {}
    specs = []
    for obj in objects:
        rgba = colour(obj.color, obj.name)
        geoms = [
            GeomSpec(type="mesh", file=Path(f"meshes/{obj.name}_part{k}.obj"))
            for k in range(len(obj.shape.parts))
        ]
        geoms.append(GeomSpec(type="mesh", file=Path(f"meshes/{obj.name}.obj"), contact=False))
        specs.append(
            ObjectSpec(
                name=obj.name,
                role=obj.role,
                pos=(float(obj.position[0]), float(obj.position[1]), obj.shape.half_height),
                yaw=float(obj.yaw),
                mass=float(obj.mass) if obj.role == "manipulated" else None,
                friction=frictions.get(obj.name, 1.0),
                rgba=rgba,
                geoms=geoms,
                look=pictures.get(obj.name),
            )
        )
    data = {
        **base,
        "name": settings.name or (f"{task_scene.name}_twin" if task_scene else "cell"),
        "table": {
            **(task_scene.table.model_dump(mode="python") if task_scene else {}),
            "size": tuple(float(v) for v in table.size),
            "center": tuple(float(v) for v in table.center),
            "yaw": float(table.yaw),
            "top_height": float(table.height),
            "rgba": colour(table.color, "table"),
            "image": pictures.get("table"),
        },
        "backdrop": pictures.get("backdrop"),
        "objects": [o.model_dump(mode="python") for o in specs],
        "cameras": [c.model_dump(mode="python") for c in merged],
        "provenance": {
            "built_from": str(source),
            "frames_registered": f"{model.registered}/{model.frames}",
            "tag_family": settings.tag_family,
            "intrinsics": camera.describe(),
            **(
                {"lens_refined": [float(v) for v in model.walk_camera().params]}
                if settings.refine_distortion
                else {}
            ),
            **(
                {"tag_points": {i: [float(v) for v in p] for i, p in settings.tag_points.items()}}
                if settings.tag_points
                else {
                    "tag_size_m": settings.tag_size,
                    "tag_pose": [float(v) for v in settings.tag_pose],
                }
            ),
            "alignment_residual_mm": round(1000 * alignment.residual_m, 2),
        },
    }
    return parse_spec(data, source="built scene")


def _write_meshes(objects: list[TwinObject], out: Path) -> None:
    """Each object's convex parts and its whole surface (a painted surface replaces it
    when the look is written)."""
    meshes = out / "meshes"
    meshes.mkdir(parents=True, exist_ok=True)
    for obj in objects:
        surface = o3d.geometry.TriangleMesh(obj.shape.surface)
        surface.triangle_normals = o3d.utility.Vector3dVector()  # OBJ: vertex normals only
        o3d.io.write_triangle_mesh(str(meshes / f"{obj.name}.obj"), surface)
        for k, (vertices, triangles) in enumerate(obj.shape.parts):
            part = o3d.geometry.TriangleMesh(
                o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles)
            )
            o3d.io.write_triangle_mesh(str(meshes / f"{obj.name}_part{k}.obj"), part)
