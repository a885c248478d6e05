"""The twin from a phone video: frames, structure from motion (pycolmap), metric scale
and robot-base frame from an AprilTag, table plane and objects (open3d)."""

from twinrl_sim.reconstruct.align import Similarity, TagAlignment, align_to_tag
from twinrl_sim.reconstruct.frames import CaptureError, FrameSelection, select_frames
from twinrl_sim.reconstruct.segment import ObjectCluster, TablePlane, find_objects, level_table
from twinrl_sim.reconstruct.sfm import SparseModel, run_sfm

__all__ = [
    "CaptureError",
    "FrameSelection",
    "ObjectCluster",
    "Similarity",
    "SparseModel",
    "TablePlane",
    "TagAlignment",
    "align_to_tag",
    "find_objects",
    "level_table",
    "run_sfm",
    "select_frames",
]
