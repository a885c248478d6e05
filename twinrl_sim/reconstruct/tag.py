"""Printed markers (AprilTag 36h11 by default, other AprilTag and ArUco families by
name): the image to print (or texture), detection in photos, and the corner coordinates
in the tag's own frame.

Conventions (those of OpenCV's ArUco module, which reads every family here without extra
downloads): the tag size is the edge of the black square; corners are reported in the
order top-left, top-right, bottom-right, bottom-left of the printed image; the tag frame
has its origin at the centre, x to the right, y up the printed image and z out of the
paper, so a tag lying face up on the table has z pointing up.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DEFAULT_FAMILY = "tag36h11"


@dataclass(frozen=True)
class Family:
    """A marker family: its OpenCV dictionary and its cells per edge (data + border)."""

    label: str  # how messages name it
    dictionary: int
    cells: int


FAMILIES = {
    "tag36h11": Family("AprilTag 36h11", cv2.aruco.DICT_APRILTAG_36h11, 8),
    "tag36h10": Family("AprilTag 36h10", cv2.aruco.DICT_APRILTAG_36h10, 8),
    "tag25h9": Family("AprilTag 25h9", cv2.aruco.DICT_APRILTAG_25h9, 7),
    "tag16h5": Family("AprilTag 16h5", cv2.aruco.DICT_APRILTAG_16h5, 6),
    "aruco4x4": Family("ArUco 4x4", cv2.aruco.DICT_4X4_1000, 6),
    "aruco5x5": Family("ArUco 5x5", cv2.aruco.DICT_5X5_1000, 7),
    "aruco6x6": Family("ArUco 6x6", cv2.aruco.DICT_6X6_1000, 8),
    "aruco7x7": Family("ArUco 7x7", cv2.aruco.DICT_7X7_1000, 9),
    "aruco_original": Family("ArUco original", cv2.aruco.DICT_ARUCO_ORIGINAL, 7),
}
"""The families ``tag_family`` may name."""


def family(name: str) -> Family:
    """The family called ``name`` (a key of :data:`FAMILIES`)."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ValueError(f"unknown tag family '{name}'; one of {', '.join(FAMILIES)}") from None


def _dictionary(name: str) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(family(name).dictionary)


def tag_image(
    tag_id: int = 0, cell_px: int = 32, margin_cells: int = 1, family_name: str = DEFAULT_FAMILY
) -> np.ndarray:
    """The tag as a grey uint8 image with a white margin (``margin_cells`` per side)."""
    cells = family(family_name).cells
    inner = cv2.aruco.generateImageMarker(_dictionary(family_name), tag_id, cells * cell_px)
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


def detect(
    image: np.ndarray, tag_id: int | None = None, family_name: str = DEFAULT_FAMILY
) -> list[Detection]:
    """Tags of one family in an RGB or grey image (sub-pixel corners), optionally one id."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(_dictionary(family_name), params)
    corners, ids, _ = detector.detectMarkers(grey)
    found = (
        []
        if ids is None
        else [Detection(int(i), c.reshape(4, 2)) for c, i in zip(corners, ids.ravel(), strict=True)]
    )
    return [d for d in found if tag_id is None or d.tag_id == tag_id]


def other_families_seen(image: np.ndarray, family_name: str = DEFAULT_FAMILY) -> list[str]:
    """The names of marker families other than ``family_name`` found in ``image`` (for
    error messages)."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    seen = []
    for name in FAMILIES:
        if name == family_name:
            continue
        _, ids, _ = cv2.aruco.ArucoDetector(_dictionary(name)).detectMarkers(grey)
        if ids is not None:
            seen.append(name)
    return seen
