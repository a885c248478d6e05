"""Excitation through the UR driver (ur_rtde against the emulator) gives logs the gap
workflow diagnoses like the plant's own: the servo model a twin lacks is named, and a
twin with a UR's tracking servos names the arm's hidden delay within 20 %, once the
command link's lag (measured from the targets the controller echoes, package by
package) is set apart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.robot.test_ur_cell import EMULATED, write_cell
from twinrl_data.session import Session
from twinrl_data.streams import read_live_episode
from twinrl_robot.excitation import ExcitationSettings, run_excitation
from twinrl_robot.ur.emulator.harness import EmulatorProcess
from twinrl_sim.gap.diagnose import diagnose
from twinrl_sim.gap.identify import WindowReplay
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.tasks import make_task

pytestmark = [
    *EMULATED,
    pytest.mark.slow,  # an excitation session in real time and two diagnoses: ~1.5 min
]
HIDDEN_DELAY = 0.03  # s, the emulated arm's command-to-motion latency
SCENE = make_task("pick_place").scene
ALLOWED = ["actuator_delay", "servo_lead", "payload", "joint_friction"]


def _twin(servo: str):
    """The twin with ``servo`` following, feeding its model forward as the arm does (its
    logged torques hold the arm's weight), so that only how the servos follow differs."""
    physics = SCENE.physics.model_copy(update={"servo": servo, "feedforward": "model"})
    return SCENE.model_copy(update={"physics": physics})


def _excite(folder: Path, effects: dict) -> list:
    """Three 6 s excitation episodes recorded through the driver from an emulated arm
    with ``effects`` hidden in it."""
    folder.mkdir()
    hidden = folder / "hidden.yaml"
    hidden.write_text(yaml.safe_dump(effects))
    cell = write_cell(folder)
    session = Session.create(folder / "session")
    with EmulatorProcess(cell, effects=hidden):
        run_excitation(
            "pick_place",
            world="real",
            cell=cell,
            emulated=True,
            episodes=3,
            settings=ExcitationSettings(duration=6.0),
            session=session,
            seed=1,
        )
    return [read_live_episode(p, images=False) for p in session.episode_paths()]


# Real time: the emulated controller's link jitter grows with the host's load, and with
# other tests beside it the tracking twin's start ratio passed 0.75 (0.757 once).
@pytest.mark.realtime
# Known failure (docs/results/gap-diagnoses.md, "Measured again"): the tracking twin's
# delay is fitted right (29.6 of 30 ms) but not named, its held-out gain 4.5 % under the
# 5 % bar: the emulated arm's speeds and torques jitter from one 2 ms package to the next
# more than a twin driven by the host's targets follows. Driving the twin with the
# controller's own targets would fix it. Strict: when it passes, the mark must go. It
# runs in `make test-long`, as it cannot fail CI.
@pytest.mark.long
@pytest.mark.xfail(
    strict=True,
    reason="the delay is fitted but not named: the emulated arm's speed jitter dominates",
)
def test_excitation_through_the_driver_is_diagnosed_like_the_plants(tmp_path: Path) -> None:
    delayed = _excite(tmp_path / "delayed", {"actuator_delay": {"seconds": HIDDEN_DELAY}})
    # A twin whose servos hold each target lacks what the arm does: it is named first.
    holding = diagnose(delayed, _twin("hold"), allowed=ALLOWED)
    assert holding.candidates[0].effect == "servo_lead"
    # With a UR's tracking servos the twin starts closer, and the delay is named. The
    # gaps include the link's jitter, which varies with the host's load: the ratio was
    # below 0.6 in runs here and 0.67 in one fresh-clone CI run.
    tracking = diagnose(delayed, _twin("track"), allowed=ALLOWED)
    assert tracking.gap_before < 0.75 * holding.gap_before
    assert [s["effect"] for s in tracking.selected] == ["actuator_delay"]
    # The named delay is the arm's plus the command link's lag (the host's timing, RTDE,
    # the controller's servo period), which the log measures from the controller's every
    # package (its targets against the segments the driver sent): 2.7-3.6 ms in runs here
    # on an idle host and beside a busy process. Set apart, the arm's own delay is named
    # within 20 %: 30.3 ms idle, 28.7 ms beside a niced busy process. Measured at the
    # segments' ends instead, the lag missed a loaded host's late starts (about zero here,
    # -7 ms beside the test suite) and the arm's delay read 34-37 ms, 36.8 in a CI run.
    assert abs(tracking.command_lag) < 0.01
    named = tracking.effects["actuator_delay"]["seconds"]
    assert tracking.arm_delay == pytest.approx(named - tracking.command_lag)
    assert tracking.arm_delay == pytest.approx(HIDDEN_DELAY, rel=0.2)
    # What stays is mostly the link's jitter (when each step lands on a loaded host), which
    # no twin predicts, so how far the held-out gap shrinks depends on the host's load
    # (0.45-0.6 in runs here, 0.15-0.36 in fresh-clone CI runs). Held against a twin given
    # the true delay (the arm's plus the link's measured lag), the named one explains the
    # held-out episodes as well (42.04 against 42.13 in a run here; 72.3 with no delay).
    oracle = {"actuator_delay": {"seconds": HIDDEN_DELAY + tracking.command_lag}}
    assert tracking.gap_after < tracking.gap_before
    assert _heldout_error(tracking, tracking.effects) <= 1.05 * _heldout_error(tracking, oracle)


def _heldout_error(diagnosis, effects: dict) -> float:
    """RMS held-out residual (noise units) of the tracking twin with ``effects``."""
    replay = WindowReplay(_twin("track"), diagnosis.heldout, NoiseFloor(), fixed=effects)
    return float(np.sqrt(np.mean(replay.residuals() ** 2)))
