"""The twin from a phone video (``twinrl twin build``): frames, structure from motion
(pycolmap), metric scale and robot-base frame from AprilTags (one tag's pose, or 3+ tags'
centres), table plane and objects (open3d, CoACD), fixed cameras from photos, and the
scene spec that comes out."""

from twinrl_sim.reconstruct.align import Alignment, Similarity, align_to_points, align_to_tag
from twinrl_sim.reconstruct.frames import CaptureError, FrameSelection, select_frames
from twinrl_sim.reconstruct.objects import TwinObject
from twinrl_sim.reconstruct.pipeline import BuildSettings, build_twin
from twinrl_sim.reconstruct.result import TwinBuild
from twinrl_sim.reconstruct.segment import ObjectCluster, TablePlane, find_objects, level_table
from twinrl_sim.reconstruct.sfm import SparseModel, run_sfm

__all__ = [
    "Alignment",
    "BuildSettings",
    "CaptureError",
    "FrameSelection",
    "ObjectCluster",
    "Similarity",
    "SparseModel",
    "TablePlane",
    "TwinBuild",
    "TwinObject",
    "align_to_points",
    "align_to_tag",
    "build_twin",
    "find_objects",
    "level_table",
    "run_sfm",
    "select_frames",
]
