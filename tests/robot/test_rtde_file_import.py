"""A log recorded the way UR users record one (ur_rtde's own file recording of the
controller's packages, against the emulator) imports as an episode of the arm's motion
on the controller's clock, torques from ``target_moment``; the rows the recorder writes
on its own clock (a package twice, or one package's stamp with the next one's values)
are dropped and said, never an error."""

from __future__ import annotations

import time
import warnings

import numpy as np
import pytest

from tests.robot.test_emulator_ur_rtde import WRIST, home, host, ur  # noqa: F401 (fixtures)
from tests.robot.test_ur_cell import EMULATED
from twinrl_data import schema
from twinrl_data.errors import DataWarning
from twinrl_data.importers import import_csv, rtde_map

pytestmark = EMULATED
VARIABLES = ["timestamp", "target_q", "actual_q", "actual_qd", "actual_TCP_pose", "target_moment"]


def test_a_ur_rtde_file_recording_imports_as_the_arms_motion(ur, tmp_path):  # noqa: F811
    control, receive = ur
    path = tmp_path / "robot_data.csv"
    start = np.array(receive.getActualQ())
    target = start.copy()
    target[WRIST] += 0.4
    assert receive.startFileRecording(str(path), VARIABLES)
    time.sleep(0.3)
    control.moveJ(target.tolist(), 1.0, 4.0)  # blocking, as a user's script moves
    time.sleep(0.3)
    receive.stopFileRecording()
    cmap, torques = rtde_map(path)
    assert "target_moment" in torques
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        episode = import_csv(path, cmap)
    stamps = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0)
    distinct = np.unique(stamps)
    # Whether the recorder wrote a package twice depends on its timing against the
    # controller's; when it did, the rows are dropped and said, never an error.
    assert all(issubclass(w.category, DataWarning) for w in said)
    assert bool(said) == (len(distinct) < len(stamps))
    # On a uniform clock at the log's own rate, spanning the log.
    fps = episode.meta.fps
    assert fps == pytest.approx(1 / np.median(np.diff(distinct)), rel=1e-3)
    assert len(episode) == int((distinct[-1] - distinct[0]) * fps + 1e-6) + 1
    q = episode.data[schema.STATE][:, :6]
    assert q[0] == pytest.approx(start, abs=1e-3) and q[-1] == pytest.approx(target, abs=1e-3)
    wrist = q[:, WRIST]
    # The move in order on one clock: a row out of place would step back by up to a
    # period's motion (4e-3 rad at 1 rad/s); the servo settling at the end, by far less.
    assert np.all(np.diff(wrist) >= -2e-4)
    effort = episode.data[schema.EFFORT]
    assert np.abs(effort[:, 1]).max() > 5.0  # the shoulder carries the arm's weight
