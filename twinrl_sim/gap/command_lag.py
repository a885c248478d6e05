"""How far a real cell's command link trails its logged joint targets, measured from
what the controller echoes.

A UR cell's log carries, per step, the joint targets the controller's servo was
tracking when the step was measured (``observation.controller_target``, RTDE
``target_q``, read in the same packet as the joints). The driver streams each logged
joint target as a segment from the previous one that ends when the next step is
measured; so at that moment the controller's target falls short of the logged one by the
part of the segment still on its way: the host's timing, the network, the controller's
servo period and, on a real UR, servoJ's own smoothing. That lag is measured here, not
fitted. A diagnosis names the arm's whole command-to-motion delay (what a twin driven by
the host's commands has to reproduce) and says how much of it the link accounts for.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from twinrl_data import schema as contract

MIN_SEGMENT = 2e-3  # rad: shorter segments are mostly sensor quantisation, not lag


def command_lag(episodes: Sequence[contract.Episode]) -> float | None:
    """The median lag (s) of the controller's targets behind the logged segments, over
    every segment of at least :data:`MIN_SEGMENT`; ``None`` when no episode logs the
    controller's targets (the twin, the plant, an imported log)."""
    lags = []
    for episode in episodes:
        if contract.CONTROLLER_TARGET not in episode.data:
            continue
        sent = episode.data[contract.JOINT_TARGET].astype(float)
        echoed = episode.data[contract.CONTROLLER_TARGET].astype(float)
        # Segment k runs from sent[k - 1] to sent[k] and ends when row k + 1 is measured
        # (the first one starts from wherever the arm was reset, so it is left out).
        segment = sent[1:-1] - sent[:-2]
        missing = sent[1:-1] - echoed[2:]
        size = np.sum(segment**2, axis=1)
        long_enough = np.sqrt(size) >= MIN_SEGMENT
        fraction = np.sum(missing * segment, axis=1)[long_enough] / size[long_enough]
        lags.append(fraction / episode.meta.fps)
    measured = np.concatenate(lags) if lags else np.empty(0)
    return float(np.median(measured)) if measured.size else None
