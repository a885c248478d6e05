"""Object footprints carved from the frames' silhouettes (a visual hull).

The sparse SfM cloud thins out where an object has little texture (a banana's ends),
which shifts its centre and shortens it. Every frame still shows the whole object: its
pixels are those whose chroma (CIELAB a*, b*) is near the object's and nearer it than
the table's. Voxels around each cluster that fall inside that silhouette in at least
:data:`AGREEMENT` of the frames that see them form the object's visual hull; its
projection onto the table is the footprint, which fills in what the points miss.
Heights and the top's shape are left to the points (a hull seen from above overstates
them). An object whose colour does not stand apart from the table's (a white plate on a
grey table) is left to its points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from twinrl_sim.reconstruct.segment import ObjectCluster, TablePlane
from twinrl_sim.reconstruct.sfm import SparseModel, project

VOXEL = 0.003  # m
MARGIN = 0.04  # m searched around each cluster's points
MASK_CHROMA = 25.0  # Lab a*b* distance within which a pixel has the object's colour
MIN_CONTRAST = 25.0  # object-table chroma distance needed to carve at all
AGREEMENT = 0.75  # share of the views that must see a voxel inside the silhouette
MIN_VIEWS = 10  # views a voxel needs to be judged


def _chroma(color: np.ndarray) -> np.ndarray:
    """CIELAB (a*, b*) of one RGB colour in [0, 1], on OpenCV's 8-bit Lab scale."""
    pixel = np.round(255 * np.asarray(color)).astype(np.uint8).reshape(1, 1, 3)
    return cv2.cvtColor(pixel, cv2.COLOR_RGB2LAB)[0, 0, 1:].astype(np.float32)


@dataclass
class _Carving:
    """The voxels around one cluster and the votes the frames have cast on them."""

    chroma: np.ndarray  # (2,) the object's colour
    grid: np.ndarray  # (V, 3) voxel centres, levelled base frame
    in_sfm: np.ndarray  # (V, 3) the same in the reconstruction's frame
    inside: np.ndarray  # (V,) views that saw the voxel inside the silhouette
    seen: np.ndarray  # (V,) views that saw the voxel at all

    def observe(self, lab: np.ndarray, to_table: np.ndarray, image, camera) -> None:
        """Count one frame's votes (``lab``: its a*b* image)."""
        to_object = np.linalg.norm(lab - self.chroma, axis=2)
        mask = (to_object < MASK_CHROMA) & (to_object < to_table)
        u, v, visible = project(image, camera, self.in_sfm)
        self.seen[visible] += 1
        self.inside[visible] += mask[v[visible], u[visible]]

    def footprint(self, rng: np.random.Generator) -> np.ndarray | None:
        """xy of the occupied voxel columns, jittered; None if no voxel was kept."""
        kept = (self.seen >= MIN_VIEWS) & (self.inside >= AGREEMENT * np.maximum(self.seen, 1))
        if not kept.any():
            return None
        cells = np.unique(np.round(self.grid[kept, :2] / VOXEL).astype(int), axis=0) * VOXEL
        return cells + rng.uniform(-VOXEL / 10, VOXEL / 10, cells.shape)


def _carving(
    cluster: ObjectCluster, table: TablePlane, to_sfm: Callable[[np.ndarray], np.ndarray]
) -> _Carving:
    low = cluster.points.min(axis=0) - [MARGIN, MARGIN, 0.0]
    high = cluster.points.max(axis=0) + [MARGIN, MARGIN, 0.0]
    low[2] = table.height + VOXEL
    high[2] = table.height + max(cluster.size[2], VOXEL)
    axes = [np.arange(a, b + VOXEL / 2, VOXEL) for a, b in zip(low, high, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    votes = np.zeros(len(grid))
    return _Carving(_chroma(cluster.color), grid, to_sfm(grid), votes, votes.copy())


def carve_footprints(
    clusters: list[ObjectCluster],
    table: TablePlane,
    model: SparseModel,
    image_dir: Path,
    to_sfm: Callable[[np.ndarray], np.ndarray],
    seed: int = 0,
) -> list[np.ndarray | None]:
    """Per cluster, the (M, 2) footprint of its visual hull (xy of the occupied
    :data:`VOXEL` columns, levelled base frame), or None where it was not carved.

    ``to_sfm`` maps levelled base-frame points to the reconstruction's frame. Each frame
    is read once for all clusters. The cell centres are jittered by a tenth of a voxel
    (seeded): a regular grid is degenerate for the alpha shape's Delaunay tetrahedra."""
    table_chroma = _chroma(table.color)
    carvings = [
        _carving(cluster, table, to_sfm)
        if np.linalg.norm(_chroma(cluster.color) - table_chroma) >= MIN_CONTRAST
        else None
        for cluster in clusters
    ]
    active = [c for c in carvings if c is not None]
    if active:
        for image in model.reconstruction.images.values():
            if not image.has_pose:
                continue
            bgr = cv2.imread(str(image_dir / image.name))
            lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2LAB)[:, :, 1:].astype(np.float32)
            to_table = np.linalg.norm(lab - table_chroma, axis=2)
            camera = model.reconstruction.cameras[image.camera_id]
            for carving in active:
                carving.observe(lab, to_table, image, camera)
    rng = np.random.default_rng(seed)
    return [None if c is None else c.footprint(rng) for c in carvings]
