"""The table's extent and colour from the frames, not from its SfM points.

A plain table top has few SfM points (features need texture), so the points' extent
is a patch of the table, and it changes from run to run. Every registered frame still
shows the top: a grid of :data:`CELL` cells on the fitted plane is projected into each
view, and the view votes "table" for a cell whose pixel has the table's colour. The
colour is learned from the frames too, in the core of the points' patch: a Gaussian over
chromaticity and log brightness, fitted robustly (the core also shows tags and objects),
so a textured top tolerates its own light and dark patches while a plain white one is
told apart from a grey floor. The table is the connected region of table
cells around that core, turned to the direction its seen edges run (the points' yaw
means nothing on a plain top); each side of it counts as *seen* where the cells just
beyond it were seen and voted "not table" (otherwise the size along that side is a
lower bound, and the report says so).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from twinrl_sim.reconstruct.segment import TablePlane, planar_axes
from twinrl_sim.reconstruct.sfm import SparseModel, project

CELL = 0.01  # m: grid on the table plane
REACH = 1.5  # m searched around the points' patch of the top
MIN_VIEWS = 3  # views a cell needs before its vote counts
SMOOTH_CELLS = 5  # cells across the closing and opening of the table's cells
TABLE_SHARE = 0.6  # share of a cell's views that must see the table's colour
COLOUR_DISTANCE = 3.5  # Mahalanobis distance within which a pixel has the table's colour
MIN_SPREAD = np.array([0.008, 0.008, 0.05])  # chromaticity, log brightness: least std assumed
BEYOND = (0.02, 0.06)  # m: the band outside a side that decides whether it was seen
SIDES = ("-x", "+x", "-y", "+y")  # the table's edges, along its own axes
SHEET = 1.5  # a tag's printed sheet, in half diagonals of its black square
RING = 2.5  # the ring around a tag that shows the table, in sheets
MIN_CORE_CELLS = 500  # core cells off the tags' sheets below which the rings are used
EDGE_PERCENTILE = 10  # rows (or columns) whose end may lie beyond a side
MIN_EDGE_CELLS = 30  # seen edge cells needed to take the table's yaw from its edges


@dataclasses.dataclass(frozen=True)
class _Grid:
    """Cells on the table plane, in the table's own axes around ``origin``."""

    origin: np.ndarray  # (2,) xy, base frame
    axes: np.ndarray  # (2, 2) the table's x and y rows
    u: np.ndarray  # (nu,) cell centres along the table's x
    v: np.ndarray  # (nv,) ... along its y

    def xy(self) -> np.ndarray:
        """(nv * nu, 2) the cell centres in the base frame, rows of v, then u."""
        uu, vv = np.meshgrid(self.u, self.v)
        return self.origin + np.c_[uu.ravel(), vv.ravel()] @ self.axes


def _views(model: SparseModel) -> list:
    return [image for image in model.reconstruction.images.values() if image.has_pose]


@dataclasses.dataclass(frozen=True)
class TableColour:
    """A Gaussian over :func:`read_colour` values, fitted robustly: the core of the top
    also shows the tags and the objects standing there."""

    mean: np.ndarray  # (3,)
    inverse: np.ndarray  # (3, 3) inverse covariance

    @classmethod
    def fit(cls, samples: np.ndarray, rounds: int = 5) -> TableColour:
        mean = np.median(samples, axis=0)
        spread = np.maximum(1.4826 * np.median(np.abs(samples - mean), axis=0), MIN_SPREAD)
        model = cls(mean, np.diag(1 / spread**2))
        for _ in range(rounds):  # refit on what the last fit calls table (its mode)
            kept = samples[model.alike(samples)]
            if len(kept) < 10:
                break
            covariance = np.cov(kept.T) + np.diag(MIN_SPREAD**2)
            model = cls(kept.mean(axis=0), np.linalg.inv(covariance))
        return model

    def alike(self, values: np.ndarray) -> np.ndarray:
        """(N,) whether each of ``values`` (N, 3) has the table's colour."""
        centred = values - self.mean
        distance = np.einsum("ni,ij,nj->n", centred, self.inverse, centred)
        return distance < COLOUR_DISTANCE**2


def _sample(model: SparseModel, image, colour: np.ndarray, sfm_points: np.ndarray):
    """Per point, whether ``image`` sees it (in front, inside the frame) and its Lab."""
    u, v, seen = project(image, model.reconstruction.cameras[image.camera_id], sfm_points)
    values = np.zeros((len(sfm_points), 3), np.float32)  # unseen cells: never compared
    values[seen] = colour[v[seen], u[seen]]
    return seen, values


def read_colour(path: Path) -> np.ndarray:
    """Per pixel: chromaticity (r, g shares of r + g + b) and log brightness. Shading and
    a texture's dark patches change the brightness, not the chromaticity."""
    rgb = cv2.imread(str(path))[:, :, ::-1].astype(np.float32) + 1.0
    total = rgb.sum(axis=2)
    return np.dstack([rgb[:, :, 0] / total, rgb[:, :, 1] / total, np.log(total / 3)])


def measure_table(
    table: TablePlane,
    inlier_xy: np.ndarray,
    model: SparseModel,
    image_dir: Path,
    to_sfm: Callable[[np.ndarray], np.ndarray],
    tags: tuple[np.ndarray, ...] = (),
) -> TablePlane:
    """``table`` with its centre, size and colour measured in the frames.

    ``inlier_xy`` are the plane's SfM inliers (levelled base frame, their xy); ``to_sfm``
    maps levelled base-frame points to the reconstruction's frame; ``tags`` are the
    outlines (4, 3) of the tags lying on the table. Where the frames do not show a table
    region around the points (no views, or no colour stands out), the points' extent is
    kept and the table says so (``extent_from="points"``).

    The colour is learned in the core of the inliers, never on a tag's sheet, and in a
    ring around each tag when that core is small: on a plain top the tags hold most of
    the plane's points, and their black and white would be taken for the table's.
    """
    axes = planar_axes(table.yaw)
    local = (inlier_xy - table.center) @ axes.T
    core_low, core_high = np.percentile(local, [25, 75], axis=0)
    steps = np.arange(-REACH, REACH + CELL / 2, CELL)
    grid = _Grid(table.center, axes, steps, steps)
    cells = grid.xy()
    sfm_points = to_sfm(np.c_[cells, np.full(len(cells), table.height)])
    uu, vv = np.meshgrid(grid.u, grid.v)
    in_core = (
        (uu.ravel() >= core_low[0])
        & (uu.ravel() <= core_high[0])
        & (vv.ravel() >= core_low[1])
        & (vv.ravel() <= core_high[1])
    )
    off_sheets, rings = np.ones(len(cells), bool), np.zeros(len(cells), bool)
    for outline in tags:
        sheet = SHEET * np.max(np.linalg.norm(outline[:, :2] - outline[:, :2].mean(0), axis=1))
        distance = np.linalg.norm(cells - outline[:, :2].mean(0), axis=1)
        off_sheets &= distance > sheet
        rings |= distance < RING * sheet
    in_core &= off_sheets
    if in_core.sum() < MIN_CORE_CELLS:  # the points were the tags': look around them
        in_core |= rings & off_sheets
    # Each view's colour at every cell, read once (a frame is dropped once sampled).
    sampled = [
        _sample(model, image, read_colour(image_dir / image.name), sfm_points)
        for image in _views(model)
    ]
    # The table's colour: what the views show in the core of the points' patch.
    samples = np.concatenate(
        [values[seen & in_core] for seen, values in sampled] or [np.empty((0, 3))]
    )
    if len(samples) < 50:
        return table  # its extent_from stays "points"
    colour_model = TableColour.fit(samples)
    seen_count = np.zeros(len(cells))
    table_votes = np.zeros(len(cells))
    for seen, values in sampled:
        seen_count += seen
        table_votes += seen & colour_model.alike(values)
    shape = (len(grid.v), len(grid.u))
    judged = (seen_count >= MIN_VIEWS).reshape(shape)
    is_table = judged & (table_votes >= TABLE_SHARE * np.maximum(seen_count, 1)).reshape(shape)
    # Closing joins the top across thin seams (a tag's white border), opening drops
    # lone cells and hairlines that only happen to share the table's colour.
    kernel = np.ones((SMOOTH_CELLS, SMOOTH_CELLS), np.uint8)
    closed = cv2.morphologyEx(is_table.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    closed = cv2.morphologyEx(closed, cv2.MORPH_OPEN, kernel)
    count, labels = cv2.connectedComponents(closed, connectivity=4)
    core_labels = labels.ravel()[in_core]
    core_labels = core_labels[core_labels > 0]
    if count < 2 or len(core_labels) == 0:
        return table  # its extent_from stays "points"
    region = _fill_holes(labels == np.bincount(core_labels).argmax())
    # The plane's yaw came from its points, which on a plain top are a patch of any
    # shape: the edges the frames saw give the table's own.
    turn = _edge_turn(region, judged & ~is_table)
    yaw = table.yaw + turn
    local = np.c_[uu.ravel(), vv.ravel()] @ planar_axes(turn).T  # cells in the new axes
    low, high = _robust_extent(local[region.ravel()])
    seen_sides = _sides_seen(local, judged.ravel(), is_table.ravel(), low, high)
    return dataclasses.replace(
        table,
        center=table.center + ((low + high) / 2) @ planar_axes(yaw),
        size=high - low,
        yaw=yaw,
        color=_rgb(colour_model.mean),
        extent_from="frames",
        sides_seen=seen_sides,
    )


def _robust_extent(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rectangle's low and high corners (table axes) of region ``cells`` (N, 2):
    each side where all but :data:`EDGE_PERCENTILE` % of the region's rows (or columns)
    end, so that a few spur cells at a corner or along an edge (a blurred seam that
    shared the top's colour) do not widen the table as the outermost cells would, while
    notches (an object at the edge, a corner cut off) do not shrink it."""
    low, high = np.empty(2), np.empty(2)
    for axis in (0, 1):
        lines = np.round(cells[:, 1 - axis] / CELL).astype(int)  # rows of the other axis
        order = np.argsort(lines, kind="stable")
        starts = np.flatnonzero(np.diff(lines[order], prepend=lines[order][0] - 1))
        values = cells[order, axis]
        low[axis] = np.percentile(np.minimum.reduceat(values, starts), EDGE_PERCENTILE)
        high[axis] = np.percentile(np.maximum.reduceat(values, starts), 100 - EDGE_PERCENTILE)
    low -= CELL / 2
    high += CELL / 2
    return low, high


def _edge_turn(region: np.ndarray, not_table: np.ndarray) -> float:
    """The turn (rad, within +-45 deg) from the grid's axes to the table's edges: the
    dominant direction, modulo 90 deg, of the region's outer boundary where the frames
    saw something else beyond it (not where the views ran out, nor the outlines of the
    objects and tags standing on it). 0 with too little edge."""
    square = np.ones((3, 3), np.uint8)
    near_other = cv2.dilate(not_table.astype(np.uint8), square) > 0
    outline = region & (cv2.erode(region.astype(np.uint8), square) == 0)  # not the holes'
    border = outline & near_other
    if border.sum() < MIN_EDGE_CELLS:
        return 0.0
    smooth = cv2.GaussianBlur(region.astype(np.float32), (0, 0), 2.0)
    along_u = cv2.Sobel(smooth, cv2.CV_32F, 1, 0)[border]
    along_v = cv2.Sobel(smooth, cv2.CV_32F, 0, 1)[border]
    weights = np.hypot(along_u, along_v)
    fourfold = np.sum(weights * np.exp(4j * np.arctan2(along_v, along_u)))
    return float(np.angle(fourfold) / 4)


def _rgb(colour: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] of one :func:`read_colour` value."""
    r_share, g_share, log_brightness = colour
    total = 3 * np.exp(log_brightness)
    rgb = np.array([r_share, g_share, 1 - r_share - g_share]) * total - 1.0
    return np.clip(rgb / 255.0, 0.0, 1.0)


def _fill_holes(region: np.ndarray) -> np.ndarray:
    """``region`` with its enclosed holes (the objects and tags on the table) filled."""
    outside = np.pad(~region, 1, constant_values=True).astype(np.uint8)
    mask = np.zeros((outside.shape[0] + 2, outside.shape[1] + 2), np.uint8)
    cv2.floodFill(outside, mask, (0, 0), 2)
    return (outside != 2)[1:-1, 1:-1]


def _sides_seen(
    local: np.ndarray, judged: np.ndarray, is_table: np.ndarray, low: np.ndarray, high: np.ndarray
) -> tuple[str, ...]:
    """The sides (of :data:`SIDES`) whose outside band was mostly seen as not table;
    ``local`` (N, 2) are the cells in the table's axes, ``judged`` and ``is_table`` (N,)
    their verdicts."""
    near, far = BEYOND
    uu, vv = local.T
    within_u = (uu >= low[0]) & (uu <= high[0])
    within_v = (vv >= low[1]) & (vv <= high[1])
    bands = {
        "-x": within_v & (uu < low[0] - near) & (uu >= low[0] - far),
        "+x": within_v & (uu > high[0] + near) & (uu <= high[0] + far),
        "-y": within_u & (vv < low[1] - near) & (vv >= low[1] - far),
        "+y": within_u & (vv > high[1] + near) & (vv <= high[1] + far),
    }
    seen = []
    for side, band in bands.items():
        if band.any() and np.mean(judged[band] & ~is_table[band]) >= 0.5:
            seen.append(side)
    return tuple(seen)
