"""What a twin build produced: the record the pipeline returns and the report shows."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinrl_sim.reconstruct.align import Alignment
from twinrl_sim.reconstruct.candidates import DroppedCandidate
from twinrl_sim.reconstruct.frames import FrameSelection
from twinrl_sim.reconstruct.look import CellLook
from twinrl_sim.reconstruct.look_score import LookScore
from twinrl_sim.reconstruct.objects import TwinObject
from twinrl_sim.reconstruct.segment import TablePlane
from twinrl_sim.reconstruct.sfm import SparseModel
from twinrl_sim.spec import CameraSpec, SceneSpec


@dataclass
class TwinBuild:
    """What was built, with everything the report shows."""

    scene_path: Path
    scene: SceneSpec
    selection: FrameSelection
    model: SparseModel
    alignment: Alignment
    table: TablePlane
    objects: list[TwinObject]
    cameras: dict[str, CameraSpec]  # cameras placed from photos
    levelled: np.ndarray  # (N, 3) the cloud in the base frame
    camera_path: np.ndarray  # (F, 3) the walk's camera centres, base frame
    seconds: dict[str, float]
    size_ratio: float | None = None  # reconstructed / task object size (median)
    look: CellLook | None = None  # the pictures the twin is dressed in
    look_score: LookScore | None = None  # how much it looks like held-out frames
    dropped: list[DroppedCandidate] = field(default_factory=list)  # made no object, and why
