"""Where a shooting window starts the arm in a fast log: estimated from the rows around
the start, so that a stiff servo does not begin with a torque transient made of one
row's encoder noise."""

import numpy as np
import pytest

from tests.sim.test_gap_fit import _record_at
from twinrl_sim.build import compile_scene
from twinrl_sim.gap.identify import WindowReplay
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.gap.windows import cut_windows, smoothed_start

NOISE = NoiseFloor()


def _noisy_motion(fps: float, seconds: float = 4.0, seed: int = 0):
    """Two joints moving as an excitation does, their true angles and speeds, and what
    encoders with the noise floor's noise measure."""
    t = np.arange(round(seconds * fps)) / fps
    q = np.column_stack([0.4 * np.sin(2.1 * t), 0.25 * np.sin(3.3 * t + 1.0)])
    qd = np.column_stack([0.84 * np.cos(2.1 * t), 0.825 * np.cos(3.3 * t + 1.0)])
    rng = np.random.default_rng(seed)
    measured_q = q + rng.normal(0, NOISE.q, q.shape)
    measured_qd = qd + rng.normal(0, NOISE.qd, qd.shape)
    return q, qd, measured_q, measured_qd


def test_a_fast_logs_start_is_several_times_closer_than_one_row():
    q, qd, measured_q, measured_qd = _noisy_motion(125.0)
    rows = np.arange(0, len(q), 25)  # the episode's first row included (one-sided)
    q0, qd0 = smoothed_start(measured_q, measured_qd, rows, 125.0, NOISE)
    one_row = np.sqrt(np.mean((measured_q[rows] - q[rows]) ** 2))
    estimated = np.sqrt(np.mean((q0 - q[rows]) ** 2))
    assert estimated < one_row / 3
    assert np.sqrt(np.mean((qd0 - qd[rows]) ** 2)) < NOISE.qd


def test_a_slow_log_keeps_each_rows_measurement():
    _, _, measured_q, measured_qd = _noisy_motion(10.0)
    rows = [0, 20]
    q0, qd0 = smoothed_start(measured_q, measured_qd, rows, 10.0, NOISE)
    np.testing.assert_array_equal(q0, measured_q[rows])
    np.testing.assert_array_equal(qd0, measured_qd[rows])


def test_a_125_hz_log_replays_at_its_noise_floor_with_its_hidden_effects(tmp_path):
    """The twin given exactly the plant's hidden effects explains a 125 Hz log down to
    the sensors' noise (1 in noise units); started from one row's measurement, the
    torques' transients at the windows' starts held it at 1.7."""
    hidden = {"actuator_delay": {"seconds": 0.03}, "payload": {"mass": 2.0}}
    scene, episodes = _record_at(tmp_path / "s", 125.0, hidden, episodes=3)
    layout = compile_scene(scene).layout
    windows = cut_windows(episodes, layout, [o.name for o in scene.objects])
    residuals = WindowReplay(scene, windows, NOISE, fixed=hidden).residuals()
    assert np.sqrt(np.mean(residuals**2)) == pytest.approx(1.0, abs=0.15)
