"""How far a real cell's command link trails its logged joint targets, measured from
what the controller echoes.

A UR cell's log carries, per step, the joint targets the controller's servo was
tracking when the step was measured (``observation.controller_target``, RTDE
``target_q``, read in the same packet as the joints, whose controller time is
``observation.controller_time``). The driver streams each logged joint target as a
segment from the previous one that ends when the next step is measured, which a twin
replays as a straight line over the control period. The controller's target trails
that line by the host's timing, the network, the controller's servo period and, on a
real UR, servoJ's own smoothing. That lag is measured here, not fitted. A diagnosis
names the arm's whole command-to-motion delay (what a twin driven by the host's
commands has to reproduce) and says how much of it the link accounts for.

Two measures, the better one the log allows:

- **Over whole segments**, when the episodes carry the controller's every package (a
  live episode's ``controller`` sample stream, read with
  :func:`twinrl_data.streams.read_live_episode`): the lag
  that best moves the line, laid between the steps' controller times, onto the
  package-by-package targets. A host late with a step sends its segment late and then
  runs it faster to end on time, so the lag sits in the segment's first part; this
  measure sees it.
- **At segments' ends** otherwise: what the target still lacks when the next step is
  measured. It misses a late start that was caught up, so a loaded host's lag reads
  short (the named arm delay then reads long).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from twinrl_data import schema as contract

MIN_SEGMENT = 2e-3  # rad: shorter segments are mostly sensor quantisation, not lag
CONTROLLER_STREAM = "controller"  # a UR cell's packages (twinrl_robot.ur.sensor_streams)
TARGET_PREFIX = "target_q."  # the packages' servo targets, one entry per joint
SAME_TARGET = 1e-5  # rad: a step's echo and its package (written with fewer digits)


def command_lag(episodes: Sequence[contract.Episode]) -> float | None:
    """The lag (s) of the controller's targets behind the logged segments: over whole
    segments when every episode that logs the controller's targets carries its packages
    too, else at the segments' ends (the median over segments of at least
    :data:`MIN_SEGMENT`); ``None`` when no episode logs the controller's targets (the
    twin, the plant, an imported log)."""
    logged = [e for e in episodes if contract.CONTROLLER_TARGET in e.data]
    if not logged:
        return None
    streamed = [_package_terms(e) for e in logged]
    if all(terms is not None for terms in streamed):
        numerator = sum(terms[0] for terms in streamed)
        denominator = sum(terms[1] for terms in streamed)
        if denominator > 0:
            return float(numerator / denominator)
    return _lag_at_segment_ends(logged)


def _lag_at_segment_ends(episodes: Sequence[contract.Episode]) -> float | None:
    lags = []
    for episode in episodes:
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


def _package_terms(episode: contract.Episode) -> tuple[float, float] | None:
    """The least-squares terms (sum of residual times slope, sum of slope squared) of
    one episode's packages against its segments; ``None`` when it has no packages or
    its steps cannot be placed on their clock."""
    stream = episode.samples.get(CONTROLLER_STREAM)
    if stream is None or contract.CONTROLLER_TIME not in episode.data:
        return None
    columns = [i for i, n in enumerate(stream.names) if n.startswith(TARGET_PREFIX)]
    sent = episode.data[contract.JOINT_TARGET].astype(float)
    if len(columns) != sent.shape[1] or len(sent) < 4:
        return None
    packages = stream.values[:, columns].astype(float)
    echoed = episode.data[contract.CONTROLLER_TARGET].astype(float)
    row_times = episode.data[contract.CONTROLLER_TIME][:, 0].astype(float)
    offset = _clock_offset(stream.clock, packages, row_times, echoed)
    if offset is None:
        return None
    rows = row_times + offset
    # Segment k (k >= 1) runs from sent[k - 1] at row k's time to sent[k] at row k + 1's.
    ends, starts = rows[2:], rows[1:-1]
    change = sent[1:-1] - sent[:-2]
    inside = (stream.clock > starts[0]) & (stream.clock <= ends[-1])
    times, targets = stream.clock[inside], packages[inside]
    k = np.clip(np.searchsorted(ends, times), 0, len(ends) - 1)
    duration = np.maximum(ends[k] - starts[k], 1e-6)
    fraction = (times - starts[k]) / duration
    line = sent[:-2][k] + change[k] * fraction[:, None]
    slope = change[k] / duration[:, None]
    moving = np.linalg.norm(change[k], axis=1) >= MIN_SEGMENT
    residual = (line - targets)[moving]
    slope = slope[moving]
    return float(np.sum(residual * slope)), float(np.sum(slope * slope))


def _clock_offset(
    clock: np.ndarray, packages: np.ndarray, row_times: np.ndarray, echoed: np.ndarray
) -> float | None:
    """The controller clock of row time zero: each step's echoed targets are one of the
    packages, so the package nearest a moving step's echo gives the offset (the median
    over steps; steps whose targets barely moved are left out, as they match many)."""
    offsets = []
    for k in range(1, len(echoed)):
        if np.max(np.abs(echoed[k] - echoed[k - 1])) < MIN_SEGMENT:
            continue
        apart = np.max(np.abs(packages - echoed[k]), axis=1)
        nearest = int(np.argmin(apart))
        if apart[nearest] <= SAME_TARGET:
            offsets.append(clock[nearest] - row_times[k])
    return float(np.median(offsets)) if offsets else None
