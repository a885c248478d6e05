"""Structure from motion with pycolmap: SIFT features, sequential matching (the frames
come from one walk, so neighbours in time overlap) and incremental mapping. One camera
model is shared by all frames (one phone, fixed zoom).

Real footage breaks a mapper that must grow one model from its first pair: the mapper
may make several models (the largest is kept) and, when that is still too small, is
rerun with a more lenient initial pair. Extraction, matching and mapping run on one thread so
that the same frames and seed give the same reconstruction (see :func:`run_sfm`).

Photos from the cell's fixed cameras join the same reconstruction: each gets a camera
model of its own (its intrinsics are estimated), is matched against every frame of the
walk and, once the walk is mapped, registered into it (the walk's poses held fixed), so
its pose and focal length come out in the walk's frame."""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from twinrl_data.atomic import write_text_atomic
from twinrl_sim.reconstruct.frames import CaptureError

MIN_REGISTERED_FRACTION = 0.6
MIN_REGISTERED = 10
# The mapper's initial pair, tried in turn while too few frames register: least
# triangulation angle (deg) and inlier matches. COLMAP's default first.
INITIAL_PAIRS = ((16.0, 100), (8.0, 60), (4.0, 30))
MATCHINGS = ("sequential", "exhaustive")  # how frames are paired for matching


@dataclass
class SparseModel:
    """The largest reconstruction, as plain arrays in COLMAP's (arbitrary) world frame."""

    reconstruction: pycolmap.Reconstruction
    points: np.ndarray  # (N, 3)
    colors: np.ndarray  # (N, 3) uint8
    registered: int
    frames: int
    fixed_images: dict[str, str]  # camera name -> image name in the reconstruction
    models: int = 1  # separate models the mapper made of the walk (the largest is kept)
    attempts: int = 1  # initialisations tried (see INITIAL_PAIRS)

    def fixed_image(self, camera: str) -> pycolmap.Image:
        """The registered photo of fixed camera ``camera``."""
        name = self.fixed_images[camera]
        return next(i for i in self.reconstruction.images.values() if i.name == name)

    def walk_images(self) -> list[pycolmap.Image]:
        """The walk's registered frames by name, the fixed cameras' photos left out."""
        photos = set(self.fixed_images.values())
        registered = self.reconstruction.images.values()
        walk = [i for i in registered if i.has_pose and i.name not in photos]
        return sorted(walk, key=lambda image: image.name)

    def walk_camera(self) -> pycolmap.Camera:
        """The camera the walk's frames share, as mapping left it."""
        return self.reconstruction.cameras[self.walk_images()[0].camera_id]


def run_sfm(
    image_dir: Path,
    work_dir: Path,
    *,
    fixed_cameras: dict[str, Path] | None = None,
    seed: int = 0,
    overlap: int = 10,
    intrinsics: tuple[float, ...] | None = None,
    refine_distortion: bool = False,
    focal_prior: float | None = None,
    matching: str = "sequential",
) -> SparseModel:
    """Reconstruct the frames in ``image_dir`` (files written under ``work_dir``), with
    the photos of ``fixed_cameras`` (camera name -> image file) registered among them.

    ``intrinsics`` (fx, fy, cx, cy in pixels, then optionally OpenCV's k1, k2, p1, p2)
    are the filming camera's, when known: the walk is mapped with them held fixed
    instead of estimating its focal length and principal point; ``refine_distortion``
    estimates the lens distortion with them (starting from none where only fx, fy, cx,
    cy are given: a calibration that left the lens out). Without them,
    ``focal_prior`` (px, e.g. from EXIF) is the focal length the mapper starts from.
    ``matching``: "sequential" pairs each frame with the next ``overlap`` (a walk),
    "exhaustive" every pair (photos in no order, or a walk that closes its loop)."""
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    database.unlink(missing_ok=True)
    frame_names = sorted(p.name for p in image_dir.iterdir() if p.is_file())
    frames = len(frame_names)
    pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING)  # progress goes to our own bar
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    # One thread each: COLMAP numbers the images in the order extraction finishes them
    # and matches pairs in whatever order its threads take them, so with more threads the
    # same frames and seed map differently from run to run (2, 3 or 93 of 93 frames).
    extraction.num_threads = 1

    def extract(names: list[str], reader: pycolmap.ImageReaderOptions | None = None) -> None:
        # One call, one camera model: the walk's frames share one, each photo has its own.
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader or pycolmap.ImageReaderOptions(),
            extraction_options=extraction,
        )

    if intrinsics is not None:
        if refine_distortion and len(intrinsics) == 4:
            intrinsics = (*intrinsics, 0.0, 0.0, 0.0, 0.0)  # OpenCV's lens, from none
        extract(frame_names, _known_camera(intrinsics))
    elif focal_prior is not None:
        extract(frame_names, _focal_prior(focal_prior, image_dir / frame_names[0]))
    else:
        extract(frame_names)
    if matching not in MATCHINGS:
        raise ValueError(f"matching '{matching}' is not one of {', '.join(MATCHINGS)}")
    matcher = pycolmap.FeatureMatchingOptions()
    matcher.use_gpu = False
    matcher.num_threads = 1
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed  # each pair's RANSAC: the same seed, the same matches
    if matching == "exhaustive":
        pycolmap.match_exhaustive(
            database, matching_options=matcher, verification_options=verification
        )
    else:
        sequential = pycolmap.SequentialPairingOptions()
        sequential.overlap = overlap
        pycolmap.match_sequential(
            database,
            matching_options=matcher,
            pairing_options=sequential,
            verification_options=verification,
        )
    fixed_images = {}
    for camera, photo in (fixed_cameras or {}).items():
        name = f"camera_{camera}{Path(photo).suffix.lower()}"
        shutil.copyfile(photo, image_dir / name)
        fixed_images[camera] = name
        extract([name])
        pairs = work_dir / f"pairs_{camera}.txt"
        write_text_atomic(pairs, "".join(f"{name} {frame}\n" for frame in frame_names))
        imported = pycolmap.ImportedPairingOptions()
        imported.match_list_path = str(pairs)
        pycolmap.match_image_pairs(
            database,
            matching_options=matcher,
            pairing_options=imported,
            verification_options=verification,
        )
    # The walk is mapped first, on its own: a photo matched against every frame would
    # often seed the mapper's initial pair, and its unknown focal length can sink it.
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    # The mapper on one thread too: its bundle adjustments' sums otherwise come in
    # whatever order the threads finish, and a build on a loaded host came out with its
    # table 1.2 deg off its twin's; a 93-frame walk maps in the same 17 s either way.
    options.num_threads = 1
    options.image_names = frame_names
    estimated = (options.ba_refine_focal_length, options.ba_refine_extra_params)
    if intrinsics is not None:  # held as given (the principal point never is refined)
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = refine_distortion
    needed = max(MIN_REGISTERED, math.ceil(MIN_REGISTERED_FRACTION * frames))
    models, attempts = _map_walk(database, image_dir, work_dir, options, needed)
    walk_models = len(models)
    if models and fixed_images:  # then the photos join the walk, whose poses stay fixed
        walk_dir = work_dir / "walk_model"
        walk_dir.mkdir(parents=True, exist_ok=True)
        _largest(models).write(walk_dir)
        options.image_names = frame_names + list(fixed_images.values())
        options.fix_existing_frames = True
        options.multiple_models = False  # one model: the walk, grown by the photos
        # The photos' own intrinsics are unknown: estimated as COLMAP does by default.
        options.ba_refine_focal_length, options.ba_refine_extra_params = estimated
        models = pycolmap.incremental_mapping(
            database, image_dir, work_dir / "sparse", options, input_path=walk_dir
        )
    if not models:
        raise CaptureError(
            f"structure from motion registered none of the {frames} frames; film a textured "
            "scene with slow, steady motion and plenty of overlap between views"
        )
    best = _largest(models)
    registered_names = {i.name for i in best.images.values() if i.has_pose}
    registered = len(registered_names - set(fixed_images.values()))
    if registered < needed:
        raise CaptureError(
            f"structure from motion registered only {registered} of {frames} frames (at "
            f"least {needed} needed; {attempts} initialisations tried); move more slowly, "
            "keep the table in view and avoid plain, reflective surfaces"
        )
    for camera, name in fixed_images.items():
        if name not in registered_names:
            raise CaptureError(
                f"the photo of camera '{camera}' could not be placed in the reconstruction; "
                "take it from the camera's mount with the table and the tag in view, and "
                "film the walk-around so that it also passes that side of the table"
            )
    points = np.array([p.xyz for p in best.points3D.values()])
    colors = np.array([p.color for p in best.points3D.values()], np.uint8)
    return SparseModel(
        best, points, colors, registered, frames, fixed_images, walk_models, attempts
    )


def project(
    image: pycolmap.Image, camera: pycolmap.Camera, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel columns and rows (int) of ``points`` (N, 3, the reconstruction's frame) in
    registered ``image``, and whether each is in view: in front of the camera and inside
    its frame. A lens model diverges far outside its frame: such points are out of view."""
    in_camera = np.c_[points, np.ones(len(points))] @ image.cam_from_world().matrix().T
    ahead = in_camera[:, 2] > 1e-3
    projected = np.full((len(points), 2), -1.0)
    projected[ahead] = camera.img_from_cam(in_camera[ahead])
    projected[~np.isfinite(projected).all(axis=1)] = -1.0
    u, v = np.round(np.clip(projected, -1, 1e6)).astype(int).T  # clipped before the cast
    visible = ahead & (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
    return u, v, visible


def _largest(models: dict[int, pycolmap.Reconstruction]) -> pycolmap.Reconstruction:
    """The model with the most registered images (the first such, so runs agree)."""
    return max(models.values(), key=lambda r: r.num_reg_images())


def _map_walk(
    database: Path,
    image_dir: Path,
    work_dir: Path,
    options: pycolmap.IncrementalPipelineOptions,
    needed: int,
) -> tuple[dict[int, pycolmap.Reconstruction], int]:
    """Map the walk's frames, allowing several models, and retry with a more lenient
    initial pair while the largest registers fewer than ``needed``: on a narrow sweep
    the default pair (16 deg apart, 100 inliers) may not exist or may not grow. The
    best models found and the number of initialisations tried."""
    options.multiple_models = True  # a first pair that does not grow is not the end
    best: dict[int, pycolmap.Reconstruction] = {}
    for attempt, (angle, inliers) in enumerate(INITIAL_PAIRS, start=1):
        options.mapper.init_min_tri_angle, options.mapper.init_min_num_inliers = angle, inliers
        out = work_dir / f"walk_{attempt}"
        models = pycolmap.incremental_mapping(database, image_dir, out, options)
        if models and (
            not best or _largest(models).num_reg_images() > _largest(best).num_reg_images()
        ):
            best = models
        if best and _largest(best).num_reg_images() >= needed:
            break
    return best, attempt


def _focal_prior(focal: float, frame: Path) -> pycolmap.ImageReaderOptions:
    """Reader options starting the walk's one camera (COLMAP's default model) at focal
    length ``focal`` px with the principal point at the frame's centre; refined."""
    height, width = cv2.imread(str(frame)).shape[:2]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    reader.camera_params = f"{focal:.10g},{width / 2:.10g},{height / 2:.10g},0"
    return reader


def _known_camera(intrinsics: tuple[float, ...]) -> pycolmap.ImageReaderOptions:
    """Reader options giving the walk's frames one camera with these intrinsics."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE" if len(intrinsics) == 4 else "OPENCV"
    reader.camera_params = ",".join(f"{v:.10g}" for v in intrinsics)
    return reader
