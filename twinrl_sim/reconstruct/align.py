"""Metric scale and the robot-base frame from AprilTags on the table.

Two ways to tie the reconstruction to the robot base, both measured once by the user
with the TCP (see the README):

- one tag of known size and pose: its four corners are the reference points;
- three or more tags (any size) whose centres' base coordinates are known: the centres
  are the reference points, and the tag size is not needed.

Every tag is detected in every registered frame; each corner is triangulated from all
the views that see it (linear least squares on the normalised image rays, using COLMAP's
camera poses); the similarity transform (scale, rotation, translation) that maps the
reference points onto their base-frame coordinates is solved with open3d's point-to-point
estimation with scaling.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import mujoco
import numpy as np
import open3d as o3d

from twinrl_data.errors import SettingError
from twinrl_sim.errors import TwinError
from twinrl_sim.reconstruct.frames import CaptureError
from twinrl_sim.reconstruct.sfm import SparseModel
from twinrl_sim.reconstruct.tag import (
    DEFAULT_FAMILY,
    corners_in_tag_frame,
    detect,
    family,
    other_families_seen,
)

MIN_TAG_VIEWS = 3
CORNER_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")
# Largest RMS misfit of tag centres before their coordinates are called wrong: TCP
# touches and the reconstruction are good to 1-2 mm each.
MAX_POINT_RESIDUAL = 0.008
MIN_POINT_SPREAD = 0.05  # m the tag centres must stand off the line through them


@dataclass(frozen=True)
class Similarity:
    """``x_base = scale * rotation @ x_sfm + translation``."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def invert(self, points: np.ndarray) -> np.ndarray:
        """The inverse map: base-frame points back to the SfM frame."""
        return (np.asarray(points) - self.translation) @ self.rotation / self.scale

    def turned(self, rotation: np.ndarray, pivot: np.ndarray) -> Similarity:
        """This map followed by ``rotation`` about ``pivot`` (e.g. levelling the table)."""
        return Similarity(
            self.scale, rotation @ self.rotation, rotation @ (self.translation - pivot) + pivot
        )


@dataclass(frozen=True)
class Alignment:
    """The SfM-to-base similarity and the reference points it was solved from."""

    to_base: Similarity
    labels: tuple[str, ...]  # one per reference point: a corner, or "tag N"
    points_sfm: np.ndarray  # (K, 3) triangulated, SfM frame
    points_base: np.ndarray  # (K, 3) where the user says they are
    tag_outlines: tuple[np.ndarray, ...]  # (4, 3) corners of each tag used, base frame
    views: int  # registered frames that saw a tag used
    reference: str  # "tag pose" or "tag centres"

    @property
    def residuals(self) -> np.ndarray:
        """(K,) distance (m) of each aligned reference point from its given place."""
        return np.linalg.norm(self.to_base.apply(self.points_sfm) - self.points_base, axis=1)

    @property
    def residual_m(self) -> float:
        """RMS of :attr:`residuals`."""
        return float(np.sqrt(np.mean(self.residuals**2)))

    @property
    def pivot(self) -> np.ndarray:
        """Centre of the reference points (base frame): they lie on the table."""
        return self.points_base.mean(axis=0)


def tag_corners_in_base(tag_pose: np.ndarray, size: float) -> np.ndarray:
    """(4, 3) corners of a tag at ``tag_pose`` (x y z qw qx qy qz), detection order."""
    pose = np.asarray(tag_pose, float)
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, pose[3:] / np.linalg.norm(pose[3:]))
    return pose[:3] + corners_in_tag_frame(size) @ rotation.reshape(3, 3).T


def _triangulate(rays: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Least-squares point from (3x4 cam_from_world, normalised xy) observations."""
    rows = []
    for pose, (u, v) in rays:
        rows += [u * pose[2] - pose[0], v * pose[2] - pose[1]]
    _, _, vt = np.linalg.svd(np.array(rows))
    return vt[-1, :3] / vt[-1, 3]


@dataclass(frozen=True)
class TagSighting:
    """A tag triangulated from the registered frames."""

    corners_sfm: np.ndarray  # (4, 3) detection order
    frames: frozenset[str]  # the registered frames that saw it


def locate_tags(
    model: SparseModel, image_dir: Path, family_name: str = DEFAULT_FAMILY
) -> dict[int, TagSighting]:
    """Every tag of the family seen in at least :data:`MIN_TAG_VIEWS` registered frames."""
    rays: dict[int, list[list]] = {}
    frames: dict[int, set[str]] = {}
    for image in model.reconstruction.images.values():
        if not image.has_pose:
            continue
        rgb = cv2.cvtColor(cv2.imread(str(image_dir / image.name)), cv2.COLOR_BGR2RGB)
        camera = model.reconstruction.cameras[image.camera_id]
        pose = image.cam_from_world().matrix()
        for found in detect(rgb, family_name=family_name):
            normalised = camera.cam_from_img(found.corners.astype(float))
            per_corner = rays.setdefault(found.tag_id, [[], [], [], []])
            frames.setdefault(found.tag_id, set()).add(image.name)
            for k in range(4):
                per_corner[k].append((pose, normalised[k]))
    return {
        tag_id: TagSighting(
            np.array([_triangulate(r) for r in per_corner]), frozenset(frames[tag_id])
        )
        for tag_id, per_corner in rays.items()
        if len(frames[tag_id]) >= MIN_TAG_VIEWS
    }


def _missing_tag(
    model: SparseModel, image_dir: Path, what: str, seen: dict, family_name: str
) -> CaptureError:
    """The error for a tag that is not seen often enough, with what was seen instead."""
    if seen:
        hint = f"; tags seen: {', '.join(str(i) for i in sorted(seen))}"
    else:
        names = sorted(i.name for i in model.reconstruction.images.values() if i.has_pose)
        sample = cv2.imread(str(image_dir / names[len(names) // 2])) if names else None
        others = other_families_seen(sample, family_name) if sample is not None else []
        label = family(family_name).label
        hint = (
            f"; the frames show {family(others[0]).label} markers instead: set `tag_family` "
            f"to {others[0]}"
            if others
            else f"; lay a printed {label} tag flat on the table and keep it in view"
        )
    return CaptureError(f"{what} was found in fewer than {MIN_TAG_VIEWS} registered frames{hint}")


def _solve(points_sfm: np.ndarray, points_base: np.ndarray) -> Similarity:
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_sfm))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_base))
    pairs = o3d.utility.Vector2iVector(np.repeat(np.arange(len(points_sfm))[:, None], 2, axis=1))
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True)
    matrix = estimation.compute_transformation(source, target, pairs)
    linear = matrix[:3, :3]
    scale = float(np.cbrt(np.linalg.det(linear)))
    return Similarity(scale, linear / scale, matrix[:3, 3])


def align_to_tag(
    model: SparseModel,
    image_dir: Path,
    tag_pose: np.ndarray,
    tag_size: float,
    tag_id: int | None = None,
    family_name: str = DEFAULT_FAMILY,
) -> Alignment:
    """The similarity from the SfM frame to the robot-base frame, from one tag's pose."""
    seen = locate_tags(model, image_dir, family_name)
    if tag_id is None and len(seen) > 1:
        raise CaptureError(
            f"several tags are in view ({', '.join(str(i) for i in sorted(seen))}); say "
            "which one `tag_pose` measures with `tag_id`"
        )
    chosen = tag_id if tag_id is not None else next(iter(seen), None)
    if chosen not in seen:
        label = family(family_name).label
        what = f"the {label} tag" if tag_id is None else f"{label} id {tag_id}"
        raise _missing_tag(model, image_dir, what, seen, family_name)
    sighting = seen[chosen]
    corners_base = tag_corners_in_base(tag_pose, tag_size)
    return Alignment(
        to_base=_solve(sighting.corners_sfm, corners_base),
        labels=CORNER_NAMES,
        points_sfm=sighting.corners_sfm,
        points_base=corners_base,
        tag_outlines=(corners_base,),
        views=len(sighting.frames),
        reference="tag pose",
    )


def check_reference_points(points: dict[int, tuple[float, ...]]) -> None:
    """Refuse tag centres that cannot fix a frame: too few, malformed, or on a line."""
    if len(points) < 3:
        raise TwinError(
            f"`tag_points` was given for {len(points)} tag(s); give the centres of 3 or more "
            "tags spread over the table"
        )
    for tag_id, xyz in points.items():
        if len(xyz) != 3:
            raise SettingError("tag_points", f"{tag_id} needs 3 numbers x,y,z, got {len(xyz)}")
    centred = np.array(list(points.values()), float)
    centred -= centred.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(len(points))
    if spread < MIN_POINT_SPREAD / 2:
        raise TwinError(
            "`tag_points`: the tag centres lie (almost) on a line, which leaves the frame's "
            f"rotation open; place the tags at least {100 * MIN_POINT_SPREAD:.0f} cm off "
            "the line through the others"
        )


def align_to_points(
    model: SparseModel,
    image_dir: Path,
    points: dict[int, tuple[float, ...]],
    family_name: str = DEFAULT_FAMILY,
) -> Alignment:
    """The similarity from the SfM frame to the robot-base frame, from the base
    coordinates of 3+ tags' centres (``{tag id: (x, y, z)}``)."""
    check_reference_points(points)
    seen = locate_tags(model, image_dir, family_name)
    label = family(family_name).label
    for tag_id in points:
        if tag_id not in seen:
            raise _missing_tag(model, image_dir, f"{label} id {tag_id}", seen, family_name)
    ids = sorted(points)
    centres_sfm = np.array([seen[i].corners_sfm.mean(axis=0) for i in ids])
    centres_base = np.array([points[i] for i in ids], float)
    to_base = _solve(centres_sfm, centres_base)
    alignment = Alignment(
        to_base=to_base,
        labels=tuple(f"tag {i}" for i in ids),
        points_sfm=centres_sfm,
        points_base=centres_base,
        tag_outlines=tuple(to_base.apply(seen[i].corners_sfm) for i in ids),
        views=len(frozenset().union(*(seen[i].frames for i in ids))),
        reference="tag centres",
    )
    if alignment.residual_m > MAX_POINT_RESIDUAL:
        worst = int(np.argmax(alignment.residuals))
        raise CaptureError(
            f"the tag centres do not fit one rigid frame: {alignment.labels[worst]} lands "
            f"{1000 * alignment.residuals[worst]:.0f} mm from its centre in `tag_points` (RMS "
            f"{1000 * alignment.residual_m:.0f} mm over {len(ids)} tags); re-measure the "
            "centres with the TCP and check that each id is the tag you touched"
        )
    return alignment
