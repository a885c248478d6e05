"""How much the frames say about each object, and so how far its shape can be trusted.

A clear, glossy or plain object gives structure from motion few points; one filmed from
one side has a depth (along the view) nobody saw. The build still makes such an object,
and says so: each object carries the frames that saw it, the arc of directions they saw
it from, its points and whether its silhouette was carved, a confidence and, in words,
what is thin. A candidate without evidence a person would accept is no object: it is
dropped, and the report says which and why
(:func:`~twinrl_sim.reconstruct.candidates.judge_candidates`).

An object seen from one side and not carved is made no wider across the view than its
silhouettes' base and no deeper along the view than it is wide across it
(:func:`bound_one_sided`): its points' spread along the view is mostly their
triangulation's error (a narrow baseline places a point well across the view and
poorly along it), which made a 71 mm bottle 149 mm deep, and stray matches on what
stands behind fringe it across, which made a 100 x 70 mm box 188 mm wide.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twinrl_sim.reconstruct.align import Similarity
from twinrl_sim.reconstruct.segment import (
    FOOTPRINT_TRIM,
    ObjectCluster,
    TablePlane,
    arc_deg,
    describe_cluster,
)
from twinrl_sim.reconstruct.sfm import SparseModel, project
from twinrl_sim.reconstruct.silhouette import VOXEL, Hull

MIN_VIEWS = 10  # frames an object needs before its place is more than a glimpse
ALL_ROUND_DEG = 90.0  # arc of view directions from which an object's depth is seen
MIN_POINTS = 50  # points an uncarved object needs for its shape to be more than rough


@dataclass(frozen=True)
class ObjectEvidence:
    """What the frames gave one object."""

    views: int  # registered frames whose image holds the object's centre
    arc_deg: float  # spread of the directions (about the vertical) those frames saw it from
    points: int  # SfM points of its cluster
    carved: bool  # whether its footprint was carved from silhouettes
    doubts: tuple[str, ...]  # what is thin, one phrase each
    # the mean horizontal direction (unit xy) the frames saw it along; None: never seen
    looked_along: np.ndarray | None = field(default=None, compare=False)

    @property
    def confidence(self) -> str:
        """high (nothing thin), medium (one thing) or low (more, or barely seen)."""
        if self.views < MIN_VIEWS or len(self.doubts) >= 2:
            return "low"
        return "medium" if self.doubts else "high"

    def summary(self) -> str:
        """One line for the report's table: views, arc, points, carved."""
        carved = "carved" if self.carved else "not carved"
        return f"{self.views} views, {self.arc_deg:.0f} deg, {self.points} pts, {carved}"


def weigh_evidence(
    cluster: ObjectCluster, model: SparseModel, to_cell: Similarity
) -> ObjectEvidence:
    """The evidence for ``cluster`` (levelled base frame; ``to_cell`` maps the
    reconstruction's frame to it) in the registered frames of the walk."""
    centre = np.asarray(cluster.center, float)
    centre_sfm = to_cell.invert(centre[None])
    directions = []
    for image in model.walk_images():
        _, _, visible = project(image, model.reconstruction.cameras[image.camera_id], centre_sfm)
        if visible[0]:
            directions.append(image.projection_center())
    if directions:
        seen_from = to_cell.apply(np.array(directions)) - centre
        azimuths = np.arctan2(seen_from[:, 1], seen_from[:, 0])
        arc = arc_deg(azimuths)
        along = -np.array([np.cos(azimuths).sum(), np.sin(azimuths).sum()])
        looked_along = along / np.linalg.norm(along) if np.linalg.norm(along) > 0 else None
    else:
        arc, looked_along = 0.0, None
    carved = cluster.carved is not None
    doubts = []
    if len(directions) < MIN_VIEWS:
        doubts.append(f"seen in only {len(directions)} frames")
    if arc < ALL_ROUND_DEG:
        doubts.append(
            f"seen from one side only ({arc:.0f} deg of arc): its depth along the view is "
            "a guess (taken as at most its width across); film it from more sides"
        )
    if cluster.outline and not carved:
        doubts.append(
            f"built from its outline ({cluster.outline} streaks of points, as a clear or "
            "glossy object gives): its depth is taken as its width"
        )
    if not cluster.top_seen:
        doubts.append(
            "its top was not seen apart from what stands behind it or above the frames: "
            f"its height, {1000 * cluster.size[2]:.0f} mm, is a lower bound; film it whole, "
            "from farther or higher"
        )
    if not carved and len(cluster.points) < MIN_POINTS:
        doubts.append(
            f"only {len(cluster.points)} points and no silhouette (a clear, glossy or plain "
            "surface, or one the colour of the table): its size is rough"
        )
    return ObjectEvidence(
        len(directions), arc, len(cluster.points), carved, tuple(doubts), looked_along
    )


def bound_one_sided(
    cluster: ObjectCluster, evidence: ObjectEvidence, hull: Hull | None, table: TablePlane
) -> ObjectCluster:
    """``cluster`` bounded where it was seen from one side only and has no carved
    footprint (see the module docstring), as it was otherwise (seen all round, carved,
    joined from an outline):

    - **across the view**, its points within the band its hull's base spans (the
      columns it fills up to its points' core, seen against the table: a shadow may
      widen it, the clutter behind does not), where that keeps at least half of them;
    - **along the view**, its points' offsets from the middle of their span shrunk so
      that it is no deeper than it is wide across."""
    along_view = evidence.looked_along
    if (
        along_view is None
        or evidence.arc_deg >= ALL_ROUND_DEG
        or cluster.carved is not None
        or cluster.outline
    ):
        return cluster
    across_view = np.array([-along_view[1], along_view[0]])
    points, colours = cluster.points, cluster.point_colors
    if hull is not None and hull.base is not None and len(hull.base):
        band = hull.base @ across_view
        across = points[:, :2] @ across_view
        inside = (across >= band.min() - VOXEL) & (across <= band.max() + VOXEL)
        if inside.mean() >= 0.5:
            points = points[inside]
            colours = None if colours is None else colours[inside]
    xy = points[:, :2]
    trimmed = [FOOTPRINT_TRIM, 100 - FOOTPRINT_TRIM]
    near, far = np.percentile(xy @ along_view, trimmed)
    depth, width = far - near, float(np.ptp(np.percentile(xy @ across_view, trimmed)))
    if depth <= width and len(points) == len(cluster.points):
        return cluster
    if depth > width:
        middle = (near + far) / 2  # the footprint's centre stays where it was
        points = points.copy()
        points[:, :2] -= np.outer((xy @ along_view - middle) * (1 - width / depth), along_view)
    from_silhouettes = cluster.top_from == "silhouettes"
    return describe_cluster(
        points,
        cluster.color,
        table,
        point_colors=colours,
        hull_top=float(cluster.size[2]) if from_silhouettes else None,
        top_seen=cluster.top_seen,
    )
