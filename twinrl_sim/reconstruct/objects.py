"""Objects of the twin from their point clusters: shape, convex parts, mass, name.

- **Shape**: the cluster's points (above the table, in the object's own frame), with
  the footprint carved from the frames' silhouettes where there is one, plus their drop
  onto the table (the underside is never filmed, the object stands on its
  footprint) are closed into a surface by an alpha shape (open3d); CoACD splits it into
  convex parts, which is what MuJoCo can collide with. The mass is the parts' volume
  times a density.
- **A supplied mesh** (a separate scan or CAD, in metres) replaces the reconstructed
  shape: it is registered to its cluster with ICP (open3d, rigid: its scale is kept),
  upright, trying headings around the clock, and decomposed the same way.
- **Names**: with a task, clusters are matched to the task's objects (size and colour,
  Hungarian assignment) and take their names and roles; the rest are fixtures.

Every object's frame has its origin at the centre of its footprint, half its height
above the table, with x along its long axis: the convention of the built-in cells,
whose tasks read an object's half height from its resting ``pos``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import coacd
import mujoco
import numpy as np
import open3d as o3d
from scipy.optimize import linear_sum_assignment
from scipy.spatial import ConvexHull

from twinrl_sim.build import compile_scene
from twinrl_sim.reconstruct.evidence import ObjectEvidence
from twinrl_sim.reconstruct.frames import CaptureError
from twinrl_sim.reconstruct.segment import ROUND_ASPECT, ObjectCluster
from twinrl_sim.spec import SceneSpec

DEFAULT_DENSITY = 700.0  # kg/m^3: fruit, wood, filled plastic; override per object
ALPHA = 0.03  # m: alpha-shape radius, about the spacing of sparse SfM points
OUTLINE_RIM = 32  # points on each rim of an object built from its outline
CONVEXITY = 0.05  # CoACD concavity threshold
MAX_PARTS = 8
SCALE_MISMATCH = 1.3  # objects this much larger/smaller than the task's: a wrong tag size
ICP_DISTANCE = 0.01  # m: correspondences farther apart are outliers


@dataclass(frozen=True)
class ObjectShape:
    """An object's geometry in its own frame (see the module docstring)."""

    surface: o3d.geometry.TriangleMesh
    parts: list[tuple[np.ndarray, np.ndarray]]  # convex (vertices, triangles)
    volume: float  # m^3, of the convex parts
    half_height: float


@dataclass(frozen=True)
class TwinObject:
    """One object of the built scene."""

    name: str
    role: str
    position: np.ndarray  # (2,) footprint centre, base frame
    yaw: float  # rad; 0 for round footprints
    shape: ObjectShape
    mass: float
    color: np.ndarray  # (3,) RGB in [0, 1]
    cluster: ObjectCluster
    source: str  # "points", "points + silhouettes", or the supplied mesh file
    evidence: ObjectEvidence
    fit_rms: float | None = None  # ICP residual of a supplied mesh (m)


def heading(cluster: ObjectCluster) -> float:
    """The cluster's yaw, or 0 when its footprint is round (no long axis)."""
    long, short = cluster.size[:2]
    return 0.0 if long < ROUND_ASPECT * short else cluster.yaw


def _to_object_frame(
    points: np.ndarray, xy: np.ndarray, yaw: float, table_height: float
) -> np.ndarray:
    """Points in the frame at ``xy`` on the table turned by ``yaw``."""
    return (points - [xy[0], xy[1], table_height]) @ _yaw_matrix(yaw)


def decompose(
    surface: o3d.geometry.TriangleMesh, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Convex parts of a closed surface (CoACD), each as (vertices, triangles)."""
    coacd.set_log_level("error")
    mesh = coacd.Mesh(np.asarray(surface.vertices), np.asarray(surface.triangles))
    parts = coacd.run_coacd(mesh, threshold=CONVEXITY, max_convex_hull=MAX_PARTS, seed=seed)
    return [(np.asarray(v, float), np.asarray(f, np.int32)) for v, f in parts]


def _shape(surface: o3d.geometry.TriangleMesh, seed: int) -> ObjectShape:
    """Centre ``surface`` (already upright, x along its long axis) and decompose it."""
    vertices = np.asarray(surface.vertices)
    low, high = vertices.min(0), vertices.max(0)
    surface = o3d.geometry.TriangleMesh(surface)
    surface.translate(-(low + high) / 2)
    parts = decompose(surface, seed)
    volume = float(sum(ConvexHull(v).volume for v, _ in parts))
    return ObjectShape(surface, parts, volume, float(high[2] - low[2]) / 2)


def reconstruct_shape(
    cluster: ObjectCluster, yaw: float, table_height: float, seed: int = 0
) -> ObjectShape:
    """The closed surface of a cluster (alpha shape of its points, its carved footprint
    and their drop onto the table; lifted to its top too where the silhouettes measured
    it above the points).

    An object built from its outline's streaks has no seen back, and is as deep as it is
    wide (see :func:`~twinrl_sim.reconstruct.segment.describe_cluster`): its surface is
    the convex hull of its points and of rims as wide as its outline at its foot and top,
    a cylinder for a bottle or a glass. A surface the alpha shape could not close into a
    manifold (sparse points), which could be neither painted nor decomposed, is the
    points' convex hull."""
    points = _to_object_frame(cluster.body_points, cluster.center[:2], yaw, table_height)
    points = points[points[:, 2] <= cluster.size[2]]
    if cluster.top_from == "silhouettes":  # the hull's top, above the points: lift them
        points = np.vstack([points, points * [1.0, 1.0, 0.0] + [0.0, 0.0, cluster.size[2]]])
    if cluster.outline:
        angle = np.linspace(0, 2 * np.pi, OUTLINE_RIM, endpoint=False)
        rim = cluster.size[0] / 2 * np.c_[np.cos(angle), np.sin(angle)]
        points = np.vstack([points, np.c_[rim, np.full(len(rim), cluster.size[2])]])
    footprint = points.copy()
    footprint[:, 2] = 0.0
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack([points, footprint])))
    surface = None
    if not cluster.outline:
        surface = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(cloud, ALPHA)
    if surface is None or not _closed(surface):
        surface, _ = cloud.compute_convex_hull()
    surface.compute_vertex_normals()
    return _shape(surface, seed)


def _closed(surface: o3d.geometry.TriangleMesh) -> bool:
    """Whether ``surface`` is a closed manifold with some volume."""
    return (
        len(surface.triangles) >= 4
        and surface.is_edge_manifold(allow_boundary_edges=False)
        and surface.is_vertex_manifold()
    )


def read_mesh(path: Path) -> o3d.geometry.TriangleMesh:
    """A user's object mesh (OBJ, STL, PLY; metres); a clear error when it is not one."""
    if not path.is_file():
        raise CaptureError(f"object mesh {path} does not exist")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) < 4:
        raise CaptureError(f"object mesh {path} holds no triangle mesh (give OBJ, STL or PLY)")
    extent = np.ptp(np.asarray(mesh.vertices), axis=0).max()
    if not 0.005 < extent < 2.0:
        raise CaptureError(
            f"object mesh {path} is {extent:g} units across; meshes must be in metres "
            "(export millimetre CAD with a 0.001 scale)"
        )
    return mesh


def fit_mesh(
    mesh: o3d.geometry.TriangleMesh, cluster: ObjectCluster, table_height: float, seed: int = 0
) -> tuple[np.ndarray, float, ObjectShape, float]:
    """Register a supplied mesh to ``cluster`` (upright, rigid; scale kept).

    The mesh's own z is taken as up. Returns the footprint centre (xy), the yaw of the
    mesh's x axis, the shape in the object frame and the RMS distance of the cluster's
    points to the fitted mesh (m).
    """
    vertices = np.asarray(mesh.vertices)
    low, high = vertices.min(0), vertices.max(0)
    standing = o3d.geometry.TriangleMesh(mesh)  # footprint centre at the origin, on z = 0
    standing.translate(-np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]]))
    o3d.utility.random.seed(seed)
    model = standing.sample_points_uniformly(4000)
    observed = cluster.points - [cluster.center[0], cluster.center[1], table_height]
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(observed))
    best = None
    for start_yaw in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        guess = np.eye(4)
        guess[:3, :3] = _yaw_matrix(-start_yaw)
        result = o3d.pipelines.registration.registration_icp(
            source,
            model,
            3 * ICP_DISTANCE,
            guess,
            o3d.pipelines.registration.TransformationEstimationPointToPoint(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60),
        )
        if best is None or (result.fitness, -result.inlier_rmse) > (
            best.fitness,
            -best.inlier_rmse,
        ):
            best = result
    to_model = best.transformation  # observed frame -> mesh frame
    to_observed = np.linalg.inv(to_model)
    yaw = float(np.arctan2(to_observed[1, 0], to_observed[0, 0]))  # kept upright
    centre = cluster.center[:2] + to_observed[:2, 3]
    distances = np.asarray(source.transform(to_model).compute_point_cloud_distance(model))
    rms = float(np.sqrt(np.mean(distances**2)))
    return centre, yaw, _shape(standing, seed), rms


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _half_extent(model: mujoco.MjModel, geom: int, rotation: np.ndarray) -> np.ndarray:
    """Exact half extent along the axes of a frame of a geom turned by ``rotation``
    (geom axes in that frame's coordinates, as columns)."""
    size = model.geom_size[geom]
    axis = rotation[:, 2]
    match int(model.geom_type[geom]):
        case mujoco.mjtGeom.mjGEOM_SPHERE:
            return np.full(3, size[0])
        case mujoco.mjtGeom.mjGEOM_CAPSULE:
            return size[1] * np.abs(axis) + size[0]
        case mujoco.mjtGeom.mjGEOM_CYLINDER:
            return size[1] * np.abs(axis) + size[0] * np.sqrt(np.clip(1 - axis**2, 0, 1))
        case mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            return np.sqrt(((rotation * size) ** 2).sum(axis=1))
        case mujoco.mjtGeom.mjGEOM_BOX:
            return np.abs(rotation) @ size[:3]
        case _:  # a mesh: its bounding box in the geom frame
            return np.abs(rotation) @ model.geom_aabb[geom][3:]


def template_sizes(scene: SceneSpec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Footprint centre (xy, base frame) and (long, short, height) of each object of
    ``scene``: the exact bounding box of its collision geoms in its own frame."""
    compiled = compile_scene(scene)
    model = compiled.model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    sizes = {}
    for obj in scene.objects:
        body = model.body(obj.name).id
        body_rotation = data.xmat[body].reshape(3, 3)
        lows, highs = [], []
        for g in np.flatnonzero(model.geom_bodyid == body):
            if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
                continue
            rotation = body_rotation.T @ data.geom_xmat[g].reshape(3, 3)
            centre = body_rotation.T @ (data.geom_xpos[g] - data.xpos[body])
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                centre = centre + rotation @ model.geom_aabb[g][:3]
            half = _half_extent(model, g, rotation)
            lows.append(centre - half)
            highs.append(centre + half)
        low, high = np.min(lows, axis=0), np.max(highs, axis=0)
        extent = high - low
        centre = data.xpos[body] + body_rotation @ ((low + high) / 2)
        sizes[obj.name] = (centre[:2], np.array([*sorted(extent[:2], reverse=True), extent[2]]))
    return sizes


def match_task_objects(
    clusters: list[ObjectCluster], task_scene: SceneSpec
) -> tuple[dict[int, str], float]:
    """Which cluster is which of the task's objects (cluster index -> name), and the
    median size ratio reconstructed/expected over the matched objects.

    Raises :class:`CaptureError` when the table holds fewer objects than the task needs,
    or when the objects come out too large or too small by the same factor (a wrong
    ``--tag-size``; a sparse reconstruction measures them 5-15 % small).
    """
    templates = {name: size for name, (_, size) in template_sizes(task_scene).items()}
    names = list(templates)
    if len(clusters) < len(names):
        raise CaptureError(
            f"the task has {len(names)} objects ({', '.join(names)}) but only "
            f"{len(clusters)} stand out on the table; film them from closer and from "
            "several sides, on a table of a different colour"
        )
    colors = {o.name: np.array(o.rgba[:3]) for o in task_scene.objects}
    cost = np.zeros((len(clusters), len(names)))
    for i, cluster in enumerate(clusters):
        measured = np.array([*sorted(cluster.size[:2], reverse=True), cluster.size[2]])
        for j, name in enumerate(names):
            shape = np.abs(np.log(measured / templates[name])).sum()
            cost[i, j] = shape + np.linalg.norm(cluster.color - colors[name])
    rows, cols = linear_sum_assignment(cost)
    ratios = [
        float(np.median(sorted(clusters[i].size[:2], reverse=True) / templates[names[j]][:2]))
        for i, j in zip(rows, cols, strict=True)
    ]
    ratio = float(np.median(ratios))
    if not 1 / SCALE_MISMATCH < ratio < SCALE_MISMATCH:
        raise CaptureError(
            f"the objects come out {ratio:.2f}x the size of the task's (median): is "
            "`tag_size` the edge of the tag's black square in metres, without the white "
            "margin? Measure the printed tag again"
        )
    return {int(i): names[j] for i, j in zip(rows, cols, strict=True)}, ratio
