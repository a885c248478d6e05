"""Structure from motion with pycolmap: SIFT features, sequential matching (the frames
come from one walk, so neighbours in time overlap) and incremental mapping. One camera
model is shared by all frames (one phone, fixed zoom)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from twinrl_sim.reconstruct.frames import CaptureError

MIN_REGISTERED_FRACTION = 0.6
MIN_REGISTERED = 10


@dataclass
class SparseModel:
    """The largest reconstruction, as plain arrays in COLMAP's (arbitrary) world frame."""

    reconstruction: pycolmap.Reconstruction
    points: np.ndarray  # (N, 3)
    colors: np.ndarray  # (N, 3) uint8
    registered: int
    frames: int


def run_sfm(image_dir: Path, work_dir: Path, *, seed: int = 0, overlap: int = 10) -> SparseModel:
    """Reconstruct the frames in ``image_dir`` (files written under ``work_dir``)."""
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    database.unlink(missing_ok=True)
    frames = len([p for p in image_dir.iterdir() if p.is_file()])
    pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING)  # progress goes to our own bar
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    pycolmap.extract_features(
        database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, extraction_options=extraction
    )
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = overlap
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing)
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.multiple_models = False
    models = pycolmap.incremental_mapping(database, image_dir, work_dir / "sparse", options)
    if not models:
        raise CaptureError(
            f"structure from motion registered none of the {frames} frames; film a textured "
            "scene with slow, steady motion and plenty of overlap between views"
        )
    best = max(models.values(), key=lambda r: r.num_reg_images())
    registered = best.num_reg_images()
    if registered < max(MIN_REGISTERED, MIN_REGISTERED_FRACTION * frames):
        raise CaptureError(
            f"structure from motion registered only {registered} of {frames} frames (at "
            f"least {max(MIN_REGISTERED, round(MIN_REGISTERED_FRACTION * frames))} needed); "
            "move more slowly, keep the table in view and avoid plain, reflective surfaces"
        )
    points = np.array([p.xyz for p in best.points3D.values()])
    colors = np.array([p.color for p in best.points3D.values()], np.uint8)
    return SparseModel(best, points, colors, registered, frames)
