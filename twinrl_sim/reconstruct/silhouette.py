"""Each object's visual hull from the frames' silhouettes: its footprint, its top, and
whether it is there at all.

The sparse SfM cloud thins out where an object has little texture (a banana's ends, a
dark bottle's glass), which shifts its centre and shortens it; where it floats on a
mismatch (a reflection, a highlight, texture seen through a clear object) it makes
objects that are not there. Every frame still shows the whole object: its pixels are
those near one of the colours of the object's points (k-means) and nearer it than the
table's: in chroma (CIELAB a*, b*) for a colour that has one, as shading changes
lightness; in lightness too for a neutral one (dark glass, a white box).
Voxels in a column over each cluster, from the table up to well above its highest
points, that fall inside that silhouette in at least :data:`AGREEMENT` of the frames
that see them (:data:`MAX_VIEWS` of them, spread over the walk) form the visual hull,
less, above its points' core, the voxels that frames saw through: a voxel crossed by
:data:`FREE_RAYS` sight lines from a frame to a point it matched beyond it is empty
(below, sight lines grazing the object would wear its outline). Above the table's
far edge an object is seen against whatever stands behind it: there the views disagree
on a busy background (it shifts with the view) and its points' sight lines pass above
the object, so the hull keeps the object's whole height and ends where it does. Where
the background has the object's colour and few points, the hull grows instead.

- **Footprint**: the cluster's points outside a hull told by chroma are strays. The
  hull's projection onto the table fills in what the points miss, where the views saw
  the object from
  :data:`ALL_ROUND_DEG` of arc (from one side the hull runs long along the view) and its
  chroma stands apart from the table's (lightness alone, which shading and shadows
  change, says where an object is, not where its outline runs on the table); otherwise
  the points' footprint is kept.
- **Top**: going up from its points' core, where the hull's cross-section falls below
  half the core's; where it instead grows past twice the core's (a background of the
  object's colour spills in), or never ends, the hull says nothing of the top. Seen from
  above, a hull overshoots the top by up to half the object's width times the tangent
  of the lowest view's elevation over it; the hull's top is taken where that bound is
  within :data:`TOP_TOLERANCE` of the height, the points' top otherwise. Where no view
  saw the space just above the top (it left every frame), the top is a lower bound.
- **Base**: the columns the hull fills up to its points' core, seen against the table
  from a camera above it, hence its outline across the view even where the walk saw it
  from one side only; higher up a busy background or the view's slant widens the hull
  (:func:`~twinrl_sim.reconstruct.evidence.bound_one_sided` takes the object's width
  across the view from there).
- **Support**: an object whose colour stands apart from the table's but whose hull is
  empty is not there (:func:`~twinrl_sim.reconstruct.candidates.judge_candidates`).

An object whose colour does not stand apart from the table's (a white plate on a white
table), or a clear one (an outline's streaks), is left to its points.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from twinrl_sim.reconstruct.segment import ObjectCluster, TablePlane, arc_deg, describe_cluster
from twinrl_sim.reconstruct.sfm import SparseModel, project

VOXEL = 0.003  # m, across
LAYER = 0.008  # m, the hull's layers
MARGIN = 0.04  # m searched around each cluster's points
HEADROOM = 1.5  # the column reaches this share of the points' height above their top
MIN_HEADROOM = 0.05  # m, and at least this
MASK_DISTANCE = 25.0  # Lab distance within which a pixel has one of the object's colours
MIN_CONTRAST = 25.0  # object-table Lab distance needed to carve at all
COLOURS = 3  # colours of an object (k-means over its points' colours)
MIN_COLOUR_SHARE = 0.15  # share of its points a colour needs to be one of the object's
AGREEMENT = 0.75  # share of the views that must see a voxel inside the silhouette
MIN_VIEWS = 10  # views a voxel needs to be judged
MAX_VIEWS = 30  # frames voted with, evenly spread over the walk (neighbours say the same)
ALL_ROUND_DEG = 90.0  # arc of views needed for the hull's footprint to be the object's
TOP_AREA = 0.5  # share of the footprint's area the hull's top layer still covers
TOP_TOLERANCE = 0.1  # the hull's top overshoot, relative to the height, that is accepted
FREE_RAYS = 2  # sight lines through a voxel to points beyond it that make it empty
SURFACE_GAP = 0.01  # m short of its point where a sight line stops carving (the point's noise)
RAY_STEP = 0.002  # m between the samples of a sight line


@dataclass(frozen=True)
class Hull:
    """What the silhouettes say about one cluster (levelled base frame)."""

    footprint: np.ndarray | None  # (M, 2) xy of the occupied voxel columns; None: empty
    outlines: bool  # the footprint is the object's (seen all round, chroma apart)
    top: float | None  # m above the table where the hull ends; None: no end was seen
    top_seen: bool  # the views saw the space above the top (else it is a lower bound)
    overshoot: float  # m, bound on how far the hull's top may lie above the object's
    chromatic: bool = False  # told by chroma, which shading does not wear: points outside
    # its footprint are strays
    base: np.ndarray | None = None  # (B, 2) xy of the columns it fills up to its points' core

    def holds(self, xy: np.ndarray) -> np.ndarray:
        """(N,) whether each of ``xy`` (N, 2) lies within a voxel of the footprint."""
        if self.footprint is None:
            return np.zeros(len(xy), bool)
        distance, _ = cKDTree(self.footprint).query(xy)
        return distance <= VOXEL

    @property
    def trusted_top(self) -> float | None:
        """The hull's top where its overshoot is within :data:`TOP_TOLERANCE`."""
        if self.top is None or self.overshoot > TOP_TOLERANCE * self.top:
            return None
        return self.top


def lab_colours(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) CIELAB (OpenCV's 8-bit scale) of RGB colours in [0, 1]."""
    pixels = np.round(255 * np.asarray(rgb).reshape(-1, 1, 3)).astype(np.uint8)
    return cv2.cvtColor(pixels, cv2.COLOR_RGB2LAB).reshape(-1, 3).astype(np.float32)


def object_colours(colours: np.ndarray, table_colour: np.ndarray, seed: int = 0) -> np.ndarray:
    """(K, 3) Lab colours of an object, from its points' RGB ``colours`` (N, 3,
    in [0, 1]): the k-means centres that hold :data:`MIN_COLOUR_SHARE` of the points and
    stand :data:`MIN_CONTRAST` apart from the table's colour; (0, 3) when none does."""
    lab = lab_colours(colours)
    if len(lab) <= COLOURS:  # each colour its own
        centres, shares = lab, np.full(len(lab), 1 / len(lab))
    else:
        cv2.setRNGSeed(seed)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
        _, labels, centres = cv2.kmeans(lab, COLOURS, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
        shares = np.bincount(labels.ravel(), minlength=COLOURS) / len(lab)
    apart = np.linalg.norm(centres - lab_colours(table_colour), axis=1) >= MIN_CONTRAST
    return centres[(shares >= MIN_COLOUR_SHARE) & apart]


@dataclass
class _Carving:
    """The voxels over one cluster and the votes the frames have cast on them."""

    colours: np.ndarray  # (K, 3) the object's Lab colours
    chromatic: np.ndarray  # (K,) whether each colour's chroma (a*, b*) alone stands apart
    grid: np.ndarray  # (V, 3) voxel centres, levelled base frame, x-major then y, z
    shape: tuple[int, int, int]  # voxels along x, y, z
    core: tuple[int, int]  # layers between its points' 25th and 75th height percentiles
    in_sfm: np.ndarray  # (V, 3) the same in the reconstruction's frame
    inside: np.ndarray  # (V,) views that saw the voxel inside the silhouette
    seen: np.ndarray  # (V,) views that saw the voxel at all
    free: np.ndarray | None = None  # (V,) sight lines through the voxel to points beyond

    def clear(self, starts: np.ndarray, ends: np.ndarray) -> None:
        """Count the sight lines (``starts`` to ``ends``, (R, 3) each) through each voxel."""
        low = self.grid[0] - [VOXEL / 2, VOXEL / 2, LAYER / 2]
        size = np.array([VOXEL, VOXEL, LAYER])
        high = low + size * self.shape
        direction = ends - starts
        with np.errstate(divide="ignore", invalid="ignore"):  # the slab method
            t0, t1 = (low - starts) / direction, (high - starts) / direction
        enter = np.nanmax(np.minimum(t0, t1), axis=1).clip(0, 1)
        leave = np.nanmin(np.maximum(t0, t1), axis=1).clip(0, 1)
        crossing = np.flatnonzero(enter < leave)
        self.free = np.zeros(len(self.grid))
        length = np.linalg.norm(direction, axis=1)
        for ray in crossing:  # a few thousand sight lines cross a column
            steps = max(int((leave[ray] - enter[ray]) * length[ray] / RAY_STEP), 1)
            t = np.linspace(enter[ray], leave[ray], steps)
            cells = np.floor((starts[ray] + t[:, None] * direction[ray] - low) / size).astype(int)
            cells = np.clip(cells, 0, np.array(self.shape) - 1)
            index = np.unique(np.ravel_multi_index(cells.T, self.shape))
            self.free[index] += 1

    def observe(self, lab: np.ndarray, to_table: np.ndarray, image, camera) -> None:
        """Count one frame's votes (``lab``: its Lab image; ``to_table``: each
        pixel's distance to the table's colour, in full and in chroma, (H, W, 2))."""
        u, v, visible = project(image, camera, self.in_sfm)
        values, table = lab[v[visible], u[visible]], to_table[v[visible], u[visible]]
        inside = np.zeros(len(values), bool)
        for colour, chromatic in zip(self.colours, self.chromatic, strict=True):
            # A colour with a chroma is told by it (shading changes lightness); a neutral
            # one (dark glass, white) by its lightness too.
            used = slice(1, 3) if chromatic else slice(0, 3)
            distance = np.linalg.norm(values[:, used] - colour[used], axis=1)
            inside |= (distance < MASK_DISTANCE) & (distance < table[:, int(chromatic)])
        self.seen[visible] += 1
        self.inside[visible] += inside

    def hull(self, cameras: np.ndarray, rng: np.random.Generator) -> Hull:
        """The hull's footprint (jittered cell centres), top and its trust; ``cameras``
        (F, 3) are the views' centres."""
        judged = (self.seen >= MIN_VIEWS).reshape(self.shape)
        kept = judged & (self.inside >= AGREEMENT * np.maximum(self.seen, 1)).reshape(self.shape)
        low, high = self.core
        if self.free is not None:  # above its points' core, seen through: empty
            kept[:, :, high + 1 :] &= (self.free < FREE_RAYS).reshape(self.shape)[:, :, high + 1 :]
        area = kept.sum(axis=(0, 1))
        core_area = np.median(area[low : high + 1])
        if core_area == 0:
            return Hull(None, False, None, False, 0.0)
        # Its body: layers as wide as its core within a factor TOP_AREA either way (wider,
        # what stands behind spills in).
        body = (area >= TOP_AREA * core_area) & (area <= core_area / TOP_AREA)
        top = high
        while top + 1 < len(area) and body[top + 1]:
            top += 1
        columns = kept[:, :, : top + 1].any(axis=2)
        cells = self.grid.reshape(*self.shape, 3)[:, :, 0, :2]
        xy = cells[columns]
        jittered = xy + rng.uniform(-VOXEL / 10, VOXEL / 10, xy.shape)
        base = cells[kept[:, :, : low + 1].any(axis=2)]
        azimuth = np.arctan2(*(cameras[:, :2] - xy.mean(axis=0)).T[::-1])
        chromatic = bool(self.chromatic.any())
        outlines = chromatic and arc_deg(azimuth) >= ALL_ROUND_DEG
        if top + 1 == len(area) or area[top + 1] >= TOP_AREA * core_area:  # no end seen
            return Hull(jittered, outlines, None, False, 0.0, chromatic, base)
        table_height = self.grid[0, 2] - LAYER / 2
        height = (top + 1) * LAYER
        width = float(np.ptp(xy, axis=0).max()) + VOXEL
        rise = np.maximum(cameras[:, 2] - (table_height + height), 0.0)
        reach = np.linalg.norm(cameras[:, :2] - xy.mean(axis=0), axis=1)
        overshoot = width / 2 * float(np.tan(np.arctan2(rise, reach).min()))
        top_seen = judged[:, :, top + 1][columns].mean() >= 0.5
        return Hull(jittered, outlines, float(height), bool(top_seen), overshoot, chromatic, base)


def join_parts(
    clusters: list[ObjectCluster], hulls: list[Hull | None], table: TablePlane
) -> tuple[list[ObjectCluster], list[Hull | None]]:
    """Candidates whose points lie (mostly) inside another's hull joined to it: parts of
    one object that its points' gaps split (a box's two textured ends), as the views'
    silhouettes hold them together. The joined hull is the union of the two."""
    clusters, hulls = list(clusters), list(hulls)
    joined = True
    while joined:
        joined = False
        for i, j in itertools.permutations(range(len(clusters)), 2):
            hull = hulls[i]
            if hull is None or hull.footprint is None or hulls[j] is None:
                continue
            if hull.holds(clusters[j].points[:, :2]).mean() < 0.5:
                continue
            clusters[i] = _join(clusters[i], clusters[j], table)
            hulls[i] = _union(hull, hulls[j])
            del clusters[j], hulls[j]
            joined = True
            break
    return clusters, hulls


def _join(a: ObjectCluster, b: ObjectCluster, table: TablePlane) -> ObjectCluster:
    points = np.vstack([a.points, b.points])
    colours = np.vstack(
        [
            np.tile(c.color, (len(c.points), 1)) if c.point_colors is None else c.point_colors
            for c in (a, b)
        ]
    )
    return describe_cluster(points, colours.mean(axis=0), table, point_colors=colours)


def _union(a: Hull, b: Hull) -> Hull:
    if b.footprint is None:
        return a
    footprint = np.vstack([a.footprint, b.footprint])
    taller = max((a, b), key=lambda h: h.top or 0.0)
    return Hull(
        footprint,
        a.outlines and b.outlines,
        taller.top,
        taller.top_seen,
        max(a.overshoot, b.overshoot),
        a.chromatic and b.chromatic,
        _stacked(a.base, b.base),
    )


def _stacked(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """Two sets of columns as one (either may be missing)."""
    if a is None or b is None:
        return a if b is None else b
    return np.vstack([a, b])


def _carving(
    cluster: ObjectCluster,
    colours: np.ndarray,
    table: TablePlane,
    to_sfm: Callable[[np.ndarray], np.ndarray],
) -> _Carving:
    # The footprint's box without the few strays that fringe every cluster.
    low = np.percentile(cluster.points, 1, axis=0) - [MARGIN, MARGIN, 0.0]
    high = np.percentile(cluster.points, 99, axis=0) + [MARGIN, MARGIN, 0.0]
    rise = max(float(cluster.points[:, 2].max()) - table.height, VOXEL)
    low[2] = table.height + LAYER / 2
    high[2] = table.height + rise + max(HEADROOM * rise, MIN_HEADROOM)
    axes = [np.arange(a, b + VOXEL / 2, VOXEL) for a, b in zip(low[:2], high[:2], strict=True)]
    axes.append(np.arange(low[2], high[2], LAYER))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    votes = np.zeros(len(grid))
    shape = (len(axes[0]), len(axes[1]), len(axes[2]))
    apart = np.linalg.norm(colours[:, 1:] - lab_colours(table.color)[0, 1:], axis=1) >= MIN_CONTRAST
    heights = np.percentile(cluster.points[:, 2], [25, 75]) - low[2]
    core = tuple(int(k) for k in np.clip(heights // LAYER, 0, shape[2] - 1))
    return _Carving(colours, apart, grid, shape, core, to_sfm(grid), votes, votes.copy())


def _sight_lines(
    model: SparseModel, from_sfm: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Every observation's sight line, from the frame's camera to :data:`SURFACE_GAP`
    short of its point (levelled base frame): the space along it is empty."""
    images = model.reconstruction.images
    centres = {i: image.projection_center() for i, image in images.items() if image.has_pose}
    starts, ends = [], []
    for point in model.reconstruction.points3D.values():
        for element in point.track.elements:
            if element.image_id in centres:
                starts.append(centres[element.image_id])
                ends.append(point.xyz)
    if not starts:
        return np.empty((0, 3)), np.empty((0, 3))
    starts, ends = from_sfm(np.array(starts)), from_sfm(np.array(ends))
    direction = ends - starts
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    keep = length[:, 0] > SURFACE_GAP
    shorter = (length - SURFACE_GAP) / np.maximum(length, 1e-9)
    return starts[keep], (starts + direction * shorter)[keep]


def carve_hulls(
    clusters: list[ObjectCluster],
    table: TablePlane,
    model: SparseModel,
    image_dir: Path,
    to_sfm: Callable[[np.ndarray], np.ndarray],
    from_sfm: Callable[[np.ndarray], np.ndarray],
    seed: int = 0,
) -> list[Hull | None]:
    """Per cluster, its :class:`Hull`, or None where it cannot be carved (its colour does
    not stand apart from the table's, or it is clear).

    ``to_sfm`` maps levelled base-frame points to the reconstruction's frame and
    ``from_sfm`` back. Each frame is read once for all clusters. The footprint's cell
    centres are jittered by a tenth of a voxel (seeded): a regular grid is degenerate for
    the alpha shape's Delaunay tetrahedra."""
    table_lab = lab_colours(table.color)[0]
    carvings = []
    for cluster in clusters:
        seen = cluster.seen_colours
        # A clear object (an outline's streaks) shows what is behind it: no colour of
        # its own to carve by.
        colours = np.empty((0, 3)) if cluster.outline else object_colours(seen, table.color, seed)
        carvings.append(_carving(cluster, colours, table, to_sfm) if len(colours) else None)
    active = [c for c in carvings if c is not None]
    views = [image for image in model.reconstruction.images.values() if image.has_pose]
    views = views[:: -(-len(views) // MAX_VIEWS)]
    if active:
        for image in views:
            rgb = cv2.imread(str(image_dir / image.name))[:, :, ::-1]
            lab = lab_colours(rgb.reshape(-1, 3) / 255.0).reshape(*rgb.shape[:2], 3)
            to_table = np.dstack(
                [
                    np.linalg.norm(lab - table_lab, axis=2),
                    np.linalg.norm(lab[:, :, 1:] - table_lab[1:], axis=2),
                ]
            )
            camera = model.reconstruction.cameras[image.camera_id]
            for carving in active:
                carving.observe(lab, to_table, image, camera)
    starts, ends = _sight_lines(model, from_sfm)
    for carving in active:
        carving.clear(starts, ends)
    cameras = from_sfm(np.array([image.projection_center() for image in views]))
    rng = np.random.default_rng(seed)
    return [None if c is None else c.hull(cameras, rng) for c in carvings]
