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
from pathlib import Path

import cv2
import numpy as np

from twinrl_sim.reconstruct.segment import ObjectCluster, TablePlane
from twinrl_sim.reconstruct.sfm import SparseModel

VOXEL = 0.003  # m
MARGIN = 0.04  # m searched around each cluster's points
MASK_CHROMA = 25.0  # Lab a*b* distance within which a pixel has the object's colour
MIN_CONTRAST = 25.0  # object-table chroma distance needed to carve at all
AGREEMENT = 0.75  # share of the views that must see a voxel inside the silhouette
MIN_VIEWS = 10  # views a voxel needs to be judged


def _chroma(rgb: np.ndarray) -> np.ndarray:
    """CIELAB (a*, b*) of uint8 RGB values of any shape (..., 3)."""
    flat = np.asarray(rgb, np.uint8).reshape(1, -1, 3)
    return (
        cv2.cvtColor(flat, cv2.COLOR_RGB2LAB)[0, :, 1:]
        .astype(np.float32)
        .reshape(*np.shape(rgb)[:-1], 2)
    )


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
    rng = np.random.default_rng(seed)
    table_chroma = _chroma(np.round(255 * table.color))
    jobs = []
    for cluster in clusters:
        chroma = _chroma(np.round(255 * cluster.color))
        if np.linalg.norm(chroma - table_chroma) < MIN_CONTRAST:
            jobs.append(None)
            continue
        low = cluster.points.min(axis=0) - [MARGIN, MARGIN, 0.0]
        high = cluster.points.max(axis=0) + [MARGIN, MARGIN, 0.0]
        low[2] = table.height + VOXEL
        high[2] = table.height + max(cluster.size[2], VOXEL)
        axes = [np.arange(a, b + VOXEL / 2, VOXEL) for a, b in zip(low, high, strict=True)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        homogeneous = np.c_[to_sfm(grid), np.ones(len(grid))]
        jobs.append((chroma, grid, homogeneous, np.zeros(len(grid)), np.zeros(len(grid))))
    if not any(jobs):
        return [None] * len(clusters)
    for image in model.reconstruction.images.values():
        if not image.has_pose:
            continue
        bgr = cv2.imread(str(image_dir / image.name))
        lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2LAB)[:, :, 1:].astype(np.float32)
        to_table = np.linalg.norm(lab - table_chroma, axis=2)
        camera = model.reconstruction.cameras[image.camera_id]
        pose = image.cam_from_world().matrix()
        for job in filter(None, jobs):
            chroma, _, homogeneous, inside, seen = job
            to_object = np.linalg.norm(lab - chroma, axis=2)
            mask = (to_object < MASK_CHROMA) & (to_object < to_table)
            in_camera = homogeneous @ pose.T
            ahead = in_camera[:, 2] > 1e-3
            uv = np.full((len(in_camera), 2), -1)
            uv[ahead] = np.round(camera.img_from_cam(in_camera[ahead])).astype(int)
            u, v = uv.T
            visible = ahead & (u >= 0) & (v >= 0) & (u < mask.shape[1]) & (v < mask.shape[0])
            seen[visible] += 1
            inside[visible] += mask[v[visible], u[visible]]
    hulls: list[np.ndarray | None] = []
    for job in jobs:
        if job is None:
            hulls.append(None)
            continue
        _, grid, _, inside, seen = job
        kept = (seen >= MIN_VIEWS) & (inside >= AGREEMENT * np.maximum(seen, 1))
        if not kept.any():
            hulls.append(None)
            continue
        cells = np.unique(np.round(grid[kept, :2] / VOXEL).astype(int), axis=0) * VOXEL
        hulls.append(cells + rng.uniform(-VOXEL / 10, VOXEL / 10, cells.shape))
    return hulls
