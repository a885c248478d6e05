"""The twin from a phone video (``twinrl twin build``): frames, structure from motion
(pycolmap), metric scale and robot-base frame from AprilTags (one tag's pose, or 3+ tags'
centres), table plane and objects (open3d, CoACD) with the evidence for each, fixed
cameras from photos, and the scene spec that comes out; and the filming camera's
calibration (``twinrl twin calibrate``).

Names load on first use: open3d, pycolmap and CoACD take seconds to import, and the
command line reads only :mod:`twinrl_sim.reconstruct.settings` to build its options.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Alignment": "align",
    "Similarity": "align",
    "align_to_points": "align",
    "align_to_tag": "align",
    "Board": "settings",
    "Calibration": "calibration",
    "calibrate": "calibration",
    "read_calibration": "calibration",
    "write_calibration": "calibration",
    "ObjectEvidence": "evidence",
    "CaptureError": "frames",
    "FrameSelection": "frames",
    "select_frames": "frames",
    "TwinObject": "objects",
    "BuildSettings": "settings",
    "build_twin": "pipeline",
    "TwinBuild": "result",
    "ObjectCluster": "segment",
    "TablePlane": "segment",
    "find_objects": "segment",
    "level_table": "segment",
    "SparseModel": "sfm",
    "run_sfm": "sfm",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'twinrl_sim.reconstruct' has no attribute '{name}'")
    value = getattr(importlib.import_module(f"twinrl_sim.reconstruct.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value
