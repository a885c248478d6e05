"""Metric scale and the robot-base frame from an AprilTag of known size and pose.

The tag is detected in every registered frame; each corner is triangulated from all the
views that see it (linear least squares on the normalised image rays, using COLMAP's
camera poses); the similarity transform (scale, rotation, translation) that maps the four
triangulated corners onto their known base-frame coordinates is solved with open3d's
point-to-point estimation with scaling. The tag pose in the base frame is measured once
by the user (touch the tag's corners with the TCP, see the README).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import mujoco
import numpy as np
import open3d as o3d

from twinrl_sim.reconstruct.frames import CaptureError
from twinrl_sim.reconstruct.sfm import SparseModel
from twinrl_sim.reconstruct.tag import corners_in_tag_frame, detect, other_families_seen

MIN_TAG_VIEWS = 3


@dataclass(frozen=True)
class Similarity:
    """``x_base = scale * rotation @ x_sfm + translation``."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation


@dataclass(frozen=True)
class TagAlignment:
    to_base: Similarity
    corners_sfm: np.ndarray  # (4, 3) triangulated corners, SfM frame
    corners_base: np.ndarray  # (4, 3) where the user says they are
    residual_m: float  # RMS corner distance after alignment (m)
    views: int


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


def locate_tag(
    model: SparseModel, image_dir: Path, tag_id: int | None = None
) -> tuple[np.ndarray, int]:
    """The tag's four corners triangulated in the SfM frame, and the number of views."""
    per_corner: list[list] = [[], [], [], []]
    views = 0
    names = []
    for image in model.reconstruction.images.values():
        if not image.has_pose:
            continue
        rgb = cv2.cvtColor(cv2.imread(str(image_dir / image.name)), cv2.COLOR_BGR2RGB)
        names.append(image.name)
        found = detect(rgb, tag_id)
        if len(found) != 1:
            continue
        views += 1
        camera = model.reconstruction.cameras[image.camera_id]
        normalised = camera.cam_from_img(found[0].corners.astype(float))
        pose = image.cam_from_world().matrix()
        for k in range(4):
            per_corner[k].append((pose, normalised[k]))
    if views < MIN_TAG_VIEWS:
        sample = cv2.cvtColor(
            cv2.imread(str(image_dir / names[len(names) // 2])), cv2.COLOR_BGR2RGB
        )
        others = other_families_seen(sample) if names else []
        hint = (
            f"; the frames show a {others[0]} marker instead: print an AprilTag 36h11"
            if others
            else "; lay a printed AprilTag 36h11 flat on the table and keep it in view"
        )
        raise CaptureError(
            f"the AprilTag 36h11 was found in {views} registered frames, at least "
            f"{MIN_TAG_VIEWS} needed{hint}"
        )
    return np.array([_triangulate(rays) for rays in per_corner]), views


def align_to_tag(
    model: SparseModel,
    image_dir: Path,
    tag_pose: np.ndarray,
    tag_size: float,
    tag_id: int | None = None,
) -> TagAlignment:
    """The similarity from the SfM frame to the robot-base frame, from the tag."""
    corners_sfm, views = locate_tag(model, image_dir, tag_id)
    corners_base = tag_corners_in_base(tag_pose, tag_size)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(corners_sfm))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(corners_base))
    pairs = o3d.utility.Vector2iVector(np.array([[k, k] for k in range(4)]))
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True)
    matrix = estimation.compute_transformation(source, target, pairs)
    linear = matrix[:3, :3]
    scale = float(np.cbrt(np.linalg.det(linear)))
    to_base = Similarity(scale, linear / scale, matrix[:3, 3])
    residual = float(
        np.sqrt(np.mean(np.sum((to_base.apply(corners_sfm) - corners_base) ** 2, axis=1)))
    )
    return TagAlignment(to_base, corners_sfm, corners_base, residual, views)
