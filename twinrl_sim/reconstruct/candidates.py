"""Which candidates are objects, and for those that are not, what they most likely are.

Points stand above the table for other reasons than an object: a shadow or a mark on
the table (the plane's noise lifts a few of their points), a highlight on a glossy top,
an object's reflection in it, what is seen through a clear object, the sheet a tag is
printed on, stray matches on what stands behind. A candidate needs its silhouette in
the views, or, where its colour is the table's and cannot be carved, enough points to
shape it (:func:`judge_candidates`). Each one dropped is named by the evidence a person
would look at (:func:`name_cause`): where it lies (on a tag's sheet, inside a clear
object's outline, beside an object) and its colour against the table's and the objects'
(CIELAB, OpenCV's 8-bit scale: lightness 0-255).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from twinrl_sim.reconstruct.evidence import MIN_POINTS
from twinrl_sim.reconstruct.segment import ObjectCluster, TablePlane
from twinrl_sim.reconstruct.silhouette import Hull, lab_colours

TAG_SHEET_MARGIN = 0.5  # of a tag's side: its printed sheet reaches this far past its outline
SHADOW_DARKER = 20.0  # lightness under the table's that makes a patch of its hue a shadow
HIGHLIGHT_BRIGHTER = 15.0  # lightness over the table's that makes a patch a highlight
BLOWN_OUT = 245.0  # lightness of a highlight that saturated the camera
TABLE_HUE = 12.0  # chroma (a*, b*) distance within which a patch has the table's hue
OBJECT_COLOUR = 25.0  # Lab distance within which a patch has a kept object's colour
NEAR_OBJECT = 0.10  # m past a kept object's footprint where its shadow or reflection lies

TAG_SHEET = "the tag's sheet"
SEEN_THROUGH = "seen through a clear object"
HIGHLIGHT = "a highlight"
SHADOW = "a shadow"
REFLECTION = "a reflection"
TABLE_TEXTURE = "texture on the table"
STRAY = "stray matches"
CAUSES = (TAG_SHEET, SEEN_THROUGH, HIGHLIGHT, SHADOW, REFLECTION, TABLE_TEXTURE, STRAY)


@dataclass(frozen=True)
class DroppedCandidate:
    """Points that stood above the table but were not made an object, and why."""

    center: np.ndarray  # (2,) xy of its footprint, levelled base frame
    size: np.ndarray  # (3,) long, short, height (m)
    points: int
    cause: str  # one of CAUSES: what it most likely is
    reason: str  # the evidence, in words


def judge_candidates(
    clusters: list[ObjectCluster],
    hulls: list[Hull | None],
    table: TablePlane,
    tags: Sequence[np.ndarray] = (),
) -> tuple[list[int], list[DroppedCandidate]]:
    """Which candidates are objects (indices into ``clusters``) and the dropped rest.

    An object needs its silhouette in the views: a candidate whose colour stands apart
    from the table's but which no silhouette holds is not there. One the table's colour
    cannot be carved: it is kept when its points outline a clear object or are enough to
    shape it (:data:`MIN_POINTS`), dropped otherwise. ``tags``: each tag's outline
    (4, 3) in the levelled base frame, for the tags lying on the table."""
    kept, unsupported = [], []
    for index, (cluster, hull) in enumerate(zip(clusters, hulls, strict=True)):
        count = len(cluster.points)
        if hull is not None and hull.footprint is None:
            evidence = f"{count} points that no silhouette holds"
        elif hull is None and not cluster.outline and count < MIN_POINTS:
            evidence = f"only {count} points, too few to shape, and no colour of its own to carve"
        else:
            kept.append(index)
            continue
        unsupported.append((cluster, evidence))
    objects = [clusters[k] for k in kept]
    dropped = []
    for cluster, evidence in unsupported:
        cause, seen = name_cause(cluster, table, tags, objects)
        dropped.append(
            DroppedCandidate(
                cluster.center[:2], cluster.size, len(cluster.points), cause, f"{seen}; {evidence}"
            )
        )
    return kept, dropped


def name_cause(
    candidate: ObjectCluster,
    table: TablePlane,
    tags: Sequence[np.ndarray],
    objects: Sequence[ObjectCluster],
) -> tuple[str, str]:
    """What a dropped candidate most likely is (one of :data:`CAUSES`) and what says so.

    Where it lies first: on a tag's printed sheet, inside the outline of a clear object
    (what is behind, seen through it). Then its colour (the median of its points')
    against the table's and the objects': lighter, a highlight; a nearby object's
    colour, its reflection (a dark object's is darker than its shadow, which is the
    table's hue dimmed); darker in the table's hue, a shadow; the table's own, texture;
    anything else, stray matches on what stands behind."""
    xy = candidate.center[:2]
    for outline in tags:
        if _on_sheet(xy, np.asarray(outline, float)):
            return TAG_SHEET, "it lies on the sheet a tag is printed on"
    for number, item in enumerate(objects, 1):
        if item.outline and _past_footprint(xy, item) <= 0.0:
            return SEEN_THROUGH, f"it lies inside clear object {number}'s outline"
    colour = np.median(lab_colours(candidate.seen_colours), axis=0)
    ground = lab_colours(table.color)[0]
    lighter = float(colour[0] - ground[0])
    hue_apart = float(np.linalg.norm(colour[1:] - ground[1:]))
    shade = f"lightness {colour[0]:.0f} against the table's {ground[0]:.0f}"
    if colour[0] >= BLOWN_OUT or lighter >= HIGHLIGHT_BRIGHTER:
        return HIGHLIGHT, f"lighter than the table ({shade})"
    near = _nearest(xy, objects)
    if near:
        index, gap = near
        own = np.median(lab_colours(objects[index].seen_colours), axis=0)
        if np.linalg.norm(colour - own) <= OBJECT_COLOUR:
            return REFLECTION, f"object {index + 1}'s colour, {gap:.2f} m from it"
    if hue_apart <= TABLE_HUE and lighter <= -SHADOW_DARKER:
        beside = f", {near[1]:.2f} m from object {near[0] + 1}" if near else ""
        return SHADOW, f"the table's hue, darker ({shade}){beside}"
    if hue_apart <= TABLE_HUE and abs(lighter) < SHADOW_DARKER:
        return TABLE_TEXTURE, f"the table's colour ({shade}), no object near"
    return STRAY, "neither the table's colour nor a nearby object's"


def _on_sheet(xy: np.ndarray, outline: np.ndarray) -> bool:
    """Whether ``xy`` lies on the sheet around a tag's ``outline`` (4, 3): within the
    square grown by :data:`TAG_SHEET_MARGIN` of its side, along the tag's own edges."""
    corners = outline[:, :2]
    centre = corners.mean(axis=0)
    edges = [corners[1] - corners[0], corners[3] - corners[0]]
    side = float(np.mean([np.linalg.norm(e) for e in edges]))
    reach = side / 2 + TAG_SHEET_MARGIN * side
    return all(abs((xy - centre) @ (e / np.linalg.norm(e))) <= reach for e in edges)


def _past_footprint(xy: np.ndarray, item: ObjectCluster) -> float:
    """m from ``xy`` to the edge of ``item``'s footprint (its long side's circle);
    negative inside."""
    return float(np.linalg.norm(xy - item.center[:2]) - item.size[0] / 2)


def _nearest(xy: np.ndarray, objects: Sequence[ObjectCluster]) -> tuple[int, float] | None:
    """(index, m past its footprint) of the object nearest ``xy``, if within
    :data:`NEAR_OBJECT`."""
    gaps = [max(_past_footprint(xy, item), 0.0) for item in objects]
    if not gaps or min(gaps) > NEAR_OBJECT:
        return None
    return int(np.argmin(gaps)), min(gaps)
