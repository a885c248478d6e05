"""The table and the objects on it, from the aligned point cloud.

- **Table**: RANSAC plane (open3d ``segment_plane``), sought near the tags' plane when
  the tags lie on the table; the cloud is then turned so that
  the plane's normal is the base frame's z (gravity), about the tag's centre so that the
  tag keeps its measured position; the table's extent is that of the plane's inliers.
- **Objects**: points above the table (and below ``max_height``). A clear or glossy
  object gives points only along its outline, where it bends or mirrors what is behind
  it: tall thin streaks of one height a width apart among the points' DBSCAN clusters
  (open3d ``cluster_dbscan``), which are joined into one object (``outline``). The
  other points are clustered by their footprints (DBSCAN on the points dropped onto the
  table): an object stands on the table, so points one above the other are one object
  however far apart in height (a label's points and a cap's, with plain glass between).
  Each large enough cluster is one object, described by its oriented footprint (its
  points seen from above, or its visual hull's where one was carved, see
  ``silhouette``), height (its points' top, or the hull's where that is trusted and
  higher), mean colour.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import mujoco
import numpy as np
import open3d as o3d

from twinrl_sim.reconstruct.frames import CaptureError

PLANE_TOLERANCE = 0.004  # m: RANSAC inlier distance
NEAR_TAGS = 0.03  # m from the tags' plane within which the table top is sought
MIN_TABLE_POINTS = 20  # points near the tags' plane needed to fit the table
MAX_TILT_FROM_TAGS = 3.0  # deg between the table's plane and the tags' that is accepted
ABOVE_TABLE = 0.004  # m: points higher than this over the plane may belong to objects
CLUSTER_EPS = 0.02  # m: DBSCAN neighbourhood of the points (a clear object's streaks)
FOOTPRINT_EPS = 0.03  # m: DBSCAN neighbourhood of footprints (objects closer are one)
MIN_CLUSTER_POINTS = 25
TOP_CELL = 0.01  # m: footprint grid of the top estimate
TOP_CELL_POINTS = 3  # points a cell needs for its median height to count
TOP_CELLS = 4  # cells needed; fewer, and the top is a high percentile of the points
TOP_PERCENTILE = 90  # over the cells' median heights
FOOTPRINT_TRIM = 1.0  # percent of the points left out at each end of a footprint
ROUND_ASPECT = 1.25  # footprints rounder than this have no heading and one diameter
STREAK_SLENDERNESS = 0.3  # a cluster whose footprint spans less of its height is a streak
STREAK_HEIGHTS_AGREE = 0.15  # relative: streaks of one outline stand as tall as each other


def planar_axes(yaw: float) -> np.ndarray:
    """(2, 2) rows: the x and y axes of a frame turned by ``yaw`` (``xy @ axes.T`` gives
    coordinates in that frame, ``local @ axes`` turns them back)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, s], [-s, c]])


def footprint_yaw(xy: np.ndarray) -> float:
    """Heading of the long axis of the convex hull of ``xy`` (rad, in (-pi/2, pi/2]).

    The hull's area moments are used rather than the points' own spread: SfM points
    bunch where the texture is richest, the hull does not care.
    """
    scale = 1000.0  # cv2 wants float32 pixels-like numbers; millimetres keep precision
    centred = (xy - xy.mean(0)) * scale
    moments = cv2.moments(cv2.convexHull(centred.astype(np.float32)))
    yaw = 0.5 * np.arctan2(2 * moments["mu11"], moments["mu20"] - moments["mu02"])
    return float((yaw + np.pi / 2) % np.pi - np.pi / 2)


@dataclass(frozen=True)
class TablePlane:
    height: float  # m, top surface in the base frame (after levelling)
    center: np.ndarray  # (2,) xy of the inliers' extent
    size: np.ndarray  # (2,) extent along the table's own x, y (m)
    yaw: float  # rad, of the table's x axis, in (-pi/4, pi/4]
    color: np.ndarray  # (3,) median RGB of the top in [0, 1]
    tilt_deg: float  # angle between the fitted normal and the tag's z before levelling
    inliers: int
    extent_from: str = "points"  # "frames" where measured in the views (table_extent)
    sides_seen: tuple[str, ...] = ()  # of "-x", "+x", "-y", "+y": edges seen in the frames


@dataclass(frozen=True)
class ObjectCluster:
    center: np.ndarray  # (3,) footprint centre; z: half the height above the table
    size: np.ndarray  # (3,) extent along its principal axes (long, short) and height
    yaw: float  # rad, of the long axis, in (-pi/2, pi/2]
    color: np.ndarray  # (3,) mean RGB in [0, 1]
    points: np.ndarray  # (N, 3) the SfM points
    carved: np.ndarray | None = None  # (M, 2) footprint carved from silhouettes, if any
    outline: int = 0  # streaks of points it was joined from (its outline's), 0: one cluster
    point_colors: np.ndarray | None = None  # (N, 3) RGB in [0, 1] of ``points``
    top_seen: bool = True  # False: no view saw above its top, its height is a lower bound
    top_from: str = "points"  # or "silhouettes": what its height was measured from

    @property
    def seen_colours(self) -> np.ndarray:
        """(K, 3) RGB in [0, 1]: its points' colours, or its mean colour where those were
        not kept."""
        return self.color[None] if self.point_colors is None else self.point_colors

    @property
    def body_points(self) -> np.ndarray:
        """The SfM points and the carved footprint on the table: what the object's
        shape is made of."""
        if self.carved is None:
            return self.points
        table_height = self.center[2] - self.size[2] / 2
        return np.vstack([self.points, np.c_[self.carved, np.full(len(self.carved), table_height)]])


def describe_cluster(
    points: np.ndarray,
    color: np.ndarray,
    table: TablePlane,
    carved: np.ndarray | None = None,
    outline: int = 0,
    *,
    point_colors: np.ndarray | None = None,
    hull_top: float | None = None,
    top_seen: bool = True,
) -> ObjectCluster:
    """An object from its points, and its carved footprint where it has one: footprint,
    heading, height.

    ``hull_top`` (m above the table) is the silhouettes' top where it can be trusted:
    the object is as tall as it, where that is above its points' top (their top then
    says where the texture ended, not the object). ``top_seen`` says whether a view saw
    above the top; without ``hull_top`` it is the points' top's (False: their top is a
    lower bound, as the silhouettes did not end).

    A carved footprint is taken whole (it is dense and has no strays); the points' is
    the 1st-99th percentile box, as a few stray matches fringe every object. A round
    footprint (aspect under ``ROUND_ASPECT``) has one diameter, its long extent: the
    long axis is where the points spread most, so uneven coverage of the rim (a pale
    plate's, from a short clip) shortens the other one more. An object joined from its
    ``outline``'s streaks is as deep as it is wide: its depth along the view was never
    seen."""
    if carved is None:
        footprint, trim = points[:, :2], FOOTPRINT_TRIM
    else:
        footprint, trim = carved, 0.0
    yaw = footprint_yaw(footprint)
    axes = planar_axes(yaw)
    low, high = np.percentile(footprint @ axes.T, [trim, 100 - trim], axis=0)
    centre_xy = ((low + high) / 2) @ axes
    # A slender object (taller than its footprint is long) has its points up its sides,
    # no top surface whose cells could say where it ends: its top is where they end.
    slender = streak_top(points) - table.height > (high - low).max()
    height = (streak_top(points) if outline or slender else top_height(points)) - table.height
    top_from = "points"
    if hull_top is not None and hull_top > height:
        height, top_from = hull_top, "silhouettes"
    elif hull_top is not None:
        top_seen = True  # the hull ends at or below the points' top: there it is
    extent = high - low
    if extent.max() < ROUND_ASPECT * extent.min() or (outline and carved is None):
        extent = np.full(2, extent.max())
    return ObjectCluster(
        center=np.array([centre_xy[0], centre_xy[1], table.height + height / 2]),
        size=np.array([extent[0], extent[1], height]),
        yaw=yaw,
        color=color,
        points=points,
        carved=carved,
        outline=outline,
        point_colors=point_colors,
        top_seen=top_seen,
        top_from=top_from,
    )


@dataclass(frozen=True)
class TagPlane:
    """The plane the tags lie on, in the base frame: where the table top must be."""

    point: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit, upward

    def distance(self, points: np.ndarray) -> np.ndarray:
        return (points - self.point) @ self.normal


def level_table(
    points: np.ndarray,
    colors: np.ndarray,
    pivot: np.ndarray,
    seed: int = 0,
    tags: TagPlane | None = None,
) -> tuple[TablePlane, np.ndarray, np.ndarray]:
    """Fit the table plane and level the cloud about ``pivot``.

    With ``tags`` (the tags lie on the table) the plane is sought among the points near
    the tags' plane only, so a wall or the floor with more points is never taken for the
    table, and a fitted plane tilted from the tags' is refused rather than levelled.
    The table's heading is that of its seen top's minimum-area rectangle (its edges),
    folded so that the table's x axis is the one nearest the base frame's.

    Returns the table, the rotation applied (3x3, about ``pivot``) and the levelled points.
    """
    o3d.utility.random.seed(seed)
    candidates = np.arange(len(points))
    if tags is not None:
        candidates = np.flatnonzero(np.abs(tags.distance(points)) < NEAR_TAGS)
        if len(candidates) < MIN_TABLE_POINTS:
            raise CaptureError(
                f"only {len(candidates)} points lie within {100 * NEAR_TAGS:g} cm of the tags' "
                "plane; film the table top around the tags, or if the tags do not lie on "
                "the table set `tags_on_table` off"
            )
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[candidates]))
    # One thread: open3d's threads draw RANSAC samples from one seeded stream in
    # whatever order they run, so planes with near-equal support swapped between runs.
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        (a, b, c, _), found = cloud.segment_plane(PLANE_TOLERANCE, 3, 2000)
    finally:
        o3d.utility.set_max_threads(threads)
    inliers = candidates[found]
    if len(inliers) < 0.2 * len(candidates):
        raise CaptureError(
            f"no table plane: only {len(inliers)} of {len(candidates)} points lie on one "
            "plane; film the table top with more of it in view"
        )
    normal = np.array([a, b, c]) / np.linalg.norm([a, b, c])
    if normal[2] < 0:
        normal = -normal
    if tags is not None:
        tilt = float(np.degrees(np.arccos(np.clip(abs(normal @ tags.normal), -1, 1))))
        if tilt > MAX_TILT_FROM_TAGS:
            raise CaptureError(
                f"the table plane near the tags is tilted {tilt:.1f} deg from the tags' plane "
                f"(more than {MAX_TILT_FROM_TAGS:g}); check that the tags lie flat on the "
                "table, or if they do not, set `tags_on_table` off"
            )
    z_to_normal = np.zeros(4)
    mujoco.mju_quatZ2Vec(z_to_normal, normal)
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, z_to_normal)
    rotation = matrix.reshape(3, 3).T  # normal -> z
    levelled = (points - pivot) @ rotation.T + pivot
    top = levelled[inliers]
    height = float(np.median(top[:, 2]))
    (_, _, angle) = cv2.minAreaRect((top[:, :2] * 1000).astype(np.float32))
    yaw = float((np.radians(angle) + np.pi / 4) % (np.pi / 2) - np.pi / 4)
    axes = planar_axes(yaw)
    low, high = np.percentile(top[:, :2] @ axes.T, [1, 99], axis=0)
    table = TablePlane(
        height=height,
        center=((low + high) / 2) @ axes,
        size=high - low,
        yaw=yaw,
        color=np.median(colors[inliers], axis=0) / 255.0,
        tilt_deg=float(np.degrees(np.arccos(np.clip(normal[2], -1, 1)))),
        inliers=len(inliers),
    )
    return table, rotation, levelled


def top_height(points: np.ndarray) -> float:
    """The height of an object's top from its points.

    The footprint is cut into :data:`TOP_CELL` cells and each cell with enough points
    gives its median height: the median cancels the reconstruction's depth noise and the
    stray matches that float above every object (a plain high percentile of the points
    made a 12 mm plate 20 mm tall). A high percentile over the cells keeps a rounded
    top's ridge, which only a few cells reach.
    """
    cells = np.floor(points[:, :2] / TOP_CELL).astype(int)
    _, cell_of, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    cell_of = cell_of.ravel()
    medians = [
        np.median(points[cell_of == k, 2]) for k in np.flatnonzero(counts >= TOP_CELL_POINTS)
    ]
    if len(medians) < TOP_CELLS:  # a small or sparse object: no cells to trust
        return streak_top(points)
    return float(np.percentile(medians, TOP_PERCENTILE))


def streak_top(points: np.ndarray) -> float:
    """The top of a streak of points, or of an outline made of them: a high percentile of
    the points (a streak has no top surface whose cells :func:`top_height` could take)."""
    return float(np.percentile(points[:, 2], 98))


def find_objects(
    points: np.ndarray, colors: np.ndarray, table: TablePlane, *, max_height: float = 1.0
) -> list[ObjectCluster]:
    """Clusters of points standing on the table, largest first: the outlines of clear
    objects (see :func:`join_outlines`), then the rest by their footprints."""
    rise = points[:, 2] - table.height
    along_table = (points[:, :2] - table.center) @ planar_axes(table.yaw).T
    on_table = np.all(np.abs(along_table) <= table.size / 2 + 0.02, axis=1)
    above = (rise > ABOVE_TABLE) & (rise < max_height) & on_table
    chosen, chosen_colors = points[above], colors[above]
    if len(chosen) < MIN_CLUSTER_POINTS:
        return []
    parts = _dbscan(chosen, CLUSTER_EPS)
    groups = [g for g in join_outlines([chosen[p] for p in parts], table.height) if len(g) > 1]
    found = [(np.concatenate([parts[i] for i in group]), len(group)) for group in groups]
    rest = np.ones(len(chosen), bool)
    for members, _ in found:  # a clear object's column is its own, whatever stands in it
        centre = chosen[members, :2].mean(axis=0)
        rest &= np.linalg.norm(chosen[:, :2] - centre, axis=1) > _span(chosen[members, :2]) / 2
    rest = np.flatnonzero(rest)
    flat = np.c_[chosen[rest, :2], np.zeros(len(rest))]
    found += [(rest[column], 0) for column in _dbscan(flat, FOOTPRINT_EPS)]
    objects = []
    for members, streaks in found:
        if len(members) < MIN_CLUSTER_POINTS:
            continue
        cluster = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(chosen[members]))
        _, keep = cluster.remove_statistical_outlier(nb_neighbors=8, std_ratio=2.0)
        rgb = chosen_colors[members][keep] / 255.0
        objects.append(
            describe_cluster(
                chosen[members][keep], rgb.mean(0), table, outline=streaks, point_colors=rgb
            )
        )
    return sorted(objects, key=lambda o: -len(o.points))


def _dbscan(points: np.ndarray, eps: float) -> list[np.ndarray]:
    """Indices of each DBSCAN cluster of ``points`` (open3d, 8 neighbours)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    labels = np.asarray(cloud.cluster_dbscan(eps, 8))
    return [np.flatnonzero(labels == label) for label in range(labels.max() + 1)]


def join_outlines(clouds: list[np.ndarray], table_height: float) -> list[list[int]]:
    """The clusters ``clouds`` grouped into objects (indices into ``clouds``), with the
    streaks that outline one object joined.

    A streak is a cluster whose footprint spans less than :data:`STREAK_SLENDERNESS` of
    its height. Streaks are joined, the nearest pair first, while their heights agree
    within :data:`STREAK_HEIGHTS_AGREE` and the joined footprint is no wider than it is
    tall (a glass or a bottle, not a row of them); every other cluster stays alone.
    """
    heights = np.array([streak_top(c) - table_height for c in clouds])
    centres = np.array([c[:, :2].mean(0) for c in clouds])

    def joinable(members: list[int]) -> bool:
        tall = heights[members]
        footprint = np.vstack([clouds[i][:, :2] for i in members])
        agree = tall.min() >= (1 - STREAK_HEIGHTS_AGREE) * tall.max()
        return agree and _span(footprint) <= tall.min()

    def gap(a: list[int], b: list[int]) -> float:
        return float(np.linalg.norm(centres[a].mean(0) - centres[b].mean(0)))

    streaks = {i for i, c in enumerate(clouds) if _span(c[:, :2]) < STREAK_SLENDERNESS * heights[i]}
    groups = [[i] for i in sorted(streaks)]
    while pairs := [
        (gap(a, b), a, b) for a, b in itertools.combinations(groups, 2) if joinable(a + b)
    ]:
        _, a, b = min(pairs, key=lambda pair: pair[0])
        groups = [g for g in groups if g is not a and g is not b] + [a + b]
    return [[i] for i in range(len(clouds)) if i not in streaks] + groups


def _span(xy: np.ndarray) -> float:
    """The longest extent of a footprint's points (m), about its own long axis."""
    local = xy @ planar_axes(footprint_yaw(xy)).T
    return float(np.ptp(local, axis=0).max())


def arc_deg(azimuths: np.ndarray) -> float:
    """The smallest arc (deg) holding every azimuth (rad): 360 minus the widest gap."""
    ordered = np.sort(np.mod(azimuths, 2 * np.pi))
    gaps = np.diff(np.r_[ordered, ordered[0] + 2 * np.pi])
    return float(np.degrees(2 * np.pi - gaps.max()))
