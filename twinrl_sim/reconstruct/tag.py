"""AprilTag 36h11 markers: the image to print (or texture), detection in photos, and the
corner coordinates in the tag's own frame.

Conventions (those of OpenCV's ArUco module, which reads AprilTag 36h11 without extra
downloads): the tag size is the edge of the black square; corners are reported in the
order top-left, top-right, bottom-right, bottom-left of the printed image; the tag frame
has its origin at the centre, x to the right, y up the printed image and z out of the
paper, so a tag lying face up on the table has z pointing up.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

FAMILY = "tag36h11"
CELLS = 8  # black border + 6 data cells + black border, per edge
# Families tried only to say what was found instead when no 36h11 tag is seen.
OTHER_FAMILIES = {
    "tag25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
    "tag36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "aruco 4x4": cv2.aruco.DICT_4X4_250,
    "aruco 5x5": cv2.aruco.DICT_5X5_250,
    "aruco 6x6": cv2.aruco.DICT_6X6_250,
}


def _dictionary(code: int = cv2.aruco.DICT_APRILTAG_36h11) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(code)


def tag_image(tag_id: int = 0, cell_px: int = 32, margin_cells: int = 1) -> np.ndarray:
    """The tag as a grey uint8 image with a white margin (``margin_cells`` per side)."""
    inner = cv2.aruco.generateImageMarker(_dictionary(), tag_id, CELLS * cell_px)
    pad = margin_cells * cell_px
    return np.pad(inner, pad, constant_values=255)


def corners_in_tag_frame(size: float) -> np.ndarray:
    """(4, 3) corner coordinates (m) in the tag frame, in detection order."""
    h = size / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class Detection:
    tag_id: int
    corners: np.ndarray  # (4, 2) pixel coordinates, detection order


def detect(image: np.ndarray, tag_id: int | None = None) -> list[Detection]:
    """36h11 tags in an RGB or grey image (sub-pixel corners), optionally one id only."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(_dictionary(), params).detectMarkers(grey)
    found = (
        []
        if ids is None
        else [Detection(int(i), c.reshape(4, 2)) for c, i in zip(corners, ids.ravel(), strict=True)]
    )
    return [d for d in found if tag_id is None or d.tag_id == tag_id]


def other_families_seen(image: np.ndarray) -> list[str]:
    """Marker families other than 36h11 found in ``image`` (for error messages)."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    seen = []
    for name, code in OTHER_FAMILIES.items():
        _, ids, _ = cv2.aruco.ArucoDetector(_dictionary(code)).detectMarkers(grey)
        if ids is not None:
            seen.append(name)
    return seen
