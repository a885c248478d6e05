"""The controller's packages handed to a live episode keep their order on the host's clock."""

from __future__ import annotations

import numpy as np

from twinrl_robot.ur.cameras import CameraRig
from twinrl_robot.ur.sensor_streams import DRIFT_WINDOW, VARIABLES, SensorStreams

COLUMNS = 1 + 6 * (len(VARIABLES) - 1)  # the timestamp, then six values per variable


class _Live:
    """Takes what the streams hand over, as the recorder's live episode does."""

    def __init__(self) -> None:
        self.received: list[np.ndarray] = []
        self.clock: list[np.ndarray] = []

    def samples(self, stream: str, received, rows, clock) -> None:
        if stream == "controller":
            self.received.append(np.asarray(received))
            self.clock.append(np.asarray(clock))


def _rows(clock: np.ndarray) -> bytes:
    values = np.zeros((len(clock), COLUMNS))
    values[:, 0] = clock
    return b"".join(b",".join(b"%.6f" % v for v in row) + b"\n" for row in values)


def test_a_lower_clock_offset_found_mid_episode_never_maps_packages_before_earlier_ones():
    streams = SensorStreams(CameraRig([]), receive=None, servo_hz=500.0)
    live = _Live()
    streams._live = live
    streams.saw(1.000, 101.010)  # offset 100.010: this read came 10 ms late
    rest, last = streams._hand_over(_rows(np.arange(1.000, 1.0099, 0.002)), -np.inf)
    streams.saw(1.010, 101.011)  # a quicker read: offset 100.001, 9 ms lower
    streams._hand_over(rest + _rows(np.arange(1.010, 1.0199, 0.002)), last)
    received, clock = np.concatenate(live.received), np.concatenate(live.clock)
    assert np.all(np.diff(clock) > 0)
    # On the host's clock too, in the packages' order and a period apart at least.
    assert np.all(np.diff(received) >= 0.002 - 1e-9), np.diff(received)
    # Each batch as close to the newest offset as the order allows.
    np.testing.assert_allclose(received[:5], clock[:5] + 100.010)
    assert received[-1] <= clock[-1] + 100.010 + 1e-9


def test_the_clock_offset_follows_a_controller_clock_that_drifts_over_hours():
    """A controller clock 50 ppm slow against the host's, read at 10 Hz for two hours
    with 1-20 ms of latency: the offset stays within 2 ms above the true one (the
    quickest reads' latency) and no further below it than the clocks drift apart in the
    window, where the lowest of the whole session would be 360 ms behind."""
    streams = SensorStreams(CameraRig([]), receive=None, servo_hz=500.0)
    rng = np.random.default_rng(0)
    host = np.arange(0.0, 2 * 3600.0, 0.1)
    controller = 5.0 + host * (1 - 50e-6)
    latency = rng.uniform(0.001, 0.020, len(host))
    errors = []
    for h, c, late in zip(host, controller, latency, strict=True):
        streams.saw(c, h + late)
        errors.append(streams.offset - (h - c))
    assert min(errors) >= -50e-6 * DRIFT_WINDOW - 1e-9
    assert max(errors[-36_000:]) < 0.002  # the last hour
    session_lowest = np.min(host + latency - controller)
    assert (host[-1] - controller[-1]) - session_lowest > 0.35
