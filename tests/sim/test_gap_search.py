"""The diagnosis's search: one Gauss-Newton step screens every candidate, and only the
most promising are fitted in full."""

import numpy as np
from mujoco.rollout import Rollout

from tests.sim.test_gap_diagnose import SCENE, _record
from twinrl_sim.build import compile_scene
from twinrl_sim.gap import search
from twinrl_sim.gap.diagnose import diagnose, split_windows
from twinrl_sim.gap.identify import WindowReplay, likelihood_term
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.gap.report import write_markdown
from twinrl_sim.gap.windows import cut_windows

HIDDEN = {"payload": {"mass": 1.5}}


def _windows(tmp_path, episodes=3):
    episodes = _record(tmp_path / "s", HIDDEN, episodes=episodes)
    layout = compile_scene(SCENE).layout
    windows = cut_windows(episodes, layout, [o.name for o in SCENE.objects])
    return episodes, windows


def test_a_first_step_explains_a_hidden_load_and_never_less_than_its_start(tmp_path):
    _, windows = _windows(tmp_path, episodes=2)
    payload = WindowReplay(SCENE, windows, NoiseFloor(), free=["payload"])
    start = likelihood_term(payload.residuals())
    x, residuals = payload.first_step()
    stepped = likelihood_term(residuals)
    assert np.allclose(residuals, payload.residuals(x))  # the residuals are those at x
    assert stepped < start - 100  # a good part of the way from the start towards the load
    mass = payload.effects_at(x)["payload"]["mass"]  # the share of the step that helps most
    assert 0.25 * HIDDEN["payload"]["mass"] < mass < 1.5 * HIDDEN["payload"]["mass"]
    # A candidate the log does not call for: its step is kept only where it helps.
    base = WindowReplay(SCENE, windows, NoiseFloor(), free=["base_offset"])
    _, residuals = base.first_step()
    assert likelihood_term(residuals) <= likelihood_term(base.residuals())


def test_a_round_fits_the_most_promising_and_reports_the_rest_screened(tmp_path):
    episodes, windows = _windows(tmp_path)
    split = split_windows(episodes, windows, 0.3, 0)
    pool = ["base_offset", "payload", "joint_damping", "servo_gain", "table_height"]
    noise = NoiseFloor()
    with Rollout(nthread=2) as rollout:
        baseline = search.score(SCENE, split.train, split.held, noise, {}, rollout)
        results = search.search_round(
            SCENE, split.train, split.held, noise, {}, pool, baseline, rollout, print
        )
    fitted = [r for r in results if not r.screened]
    screened = [r for r in results if r.screened]
    assert len(fitted) == search.SCREEN_KEEP and len(screened) == len(pool) - search.SCREEN_KEEP
    assert results[0].effect == "payload" and results[0].significant
    assert all(r.iterations == 1 and not r.significant for r in screened)
    # The screened candidates' first steps explained far less than the load's fit.
    assert all(r.bic > results[0].bic + search.BIC_MARGIN for r in screened)


def test_the_report_says_which_candidates_were_screened(tmp_path):
    episodes, _ = _windows(tmp_path)
    diagnosis = diagnose(episodes, SCENE, allowed=["payload", "base_offset", "table_height",
                                                   "joint_damping", "servo_gain"])  # fmt: skip
    assert [s["effect"] for s in diagnosis.selected] == ["payload"]
    assert any(r.screened for r in diagnosis.rounds[0])
    write_markdown(diagnosis, [], tmp_path / "report.md")
    assert "screened (one step; others explained more)" in (tmp_path / "report.md").read_text()


def test_a_tools_screen_reaches_towards_it_though_its_full_step_overshoots(tmp_path):
    """A 2.2 kg tool with its centre of gravity off the flange, logged at 125 Hz with a
    UR's servos: from a 0.1 kg start the Gauss-Newton step puts the centre of gravity
    metres away (it and its half explain less than the start); its quarter explains
    much of the tool, so the payload is not screened out behind smaller effects."""
    from tests.sim.test_gap_fit import _record_at

    tool = {"mass": 2.2, "cog": [0.04, -0.03, 0.08]}
    scene, episodes = _record_at(tmp_path / "s", 125.0, {"payload": tool})
    windows = cut_windows(episodes, compile_scene(scene).layout, [o.name for o in scene.objects])
    payload = WindowReplay(scene, windows, NoiseFloor(), free=["payload"])
    start = likelihood_term(payload.residuals())
    x, residuals = payload.first_step()
    assert likelihood_term(residuals) < start - 1000
    assert payload.effects_at(x)["payload"]["mass"] > 0.2


def outcome(diagnosis) -> tuple:
    """What a diagnosis found, without its timings."""
    rounds = [
        [(r.effect, r.params, r.heldout_error, r.bic, r.screened) for r in results]
        for results in diagnosis.rounds
    ]
    return rounds, diagnosis.selected, diagnosis.gap_before, diagnosis.gap_after


def test_a_round_on_worker_processes_finds_what_one_process_finds(tmp_path):
    episodes, _ = _windows(tmp_path)
    allowed = ["payload", "base_offset", "table_height", "joint_damping", "servo_gain"]
    alone = diagnose(episodes, SCENE, allowed=allowed)
    heard = []
    spread = diagnose(episodes, SCENE, allowed=allowed, workers=2, log=heard.append)
    assert outcome(spread) == outcome(alone)
    assert [s["effect"] for s in alone.selected] == ["payload"]
    assert any(line.startswith("screening") and "on 2 workers" in line for line in heard)
