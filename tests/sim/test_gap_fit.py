"""A gap fit whose squares end worse by the likelihood the diagnosis's BIC scores than
it started is fitted again on that likelihood's bound, which cannot end worse; one that
still does is reported as failed, never named."""

import numpy as np
import pytest
from mujoco.rollout import Rollout

from tests.sim.test_gap import _at_rate
from tests.sim.test_gap_diagnose import SCENE, _record
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_robot.excitation import ExcitationSettings, run_excitation
from twinrl_sim.build import compile_scene
from twinrl_sim.gap import identify
from twinrl_sim.gap.diagnose import diagnose
from twinrl_sim.gap.identify import WindowReplay, likelihood_term, signal_weights
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.gap.report import _verdict, write_markdown
from twinrl_sim.gap.search import fit_candidate, score
from twinrl_sim.gap.windows import cut_windows


def test_fits_that_converge_are_not_reported_failed(tmp_path):
    episodes = _record(tmp_path / "s", {"payload": {"mass": 1.5}}, episodes=2)
    layout = compile_scene(SCENE).layout
    windows = cut_windows(episodes, layout, [o.name for o in SCENE.objects])
    for effect in ("payload", "joint_friction", "actuator_delay"):
        replay = WindowReplay(SCENE, windows, NoiseFloor(), free=[effect])
        before = likelihood_term(replay.residuals())
        x, _, _ = replay.fit()
        after = likelihood_term(replay.residuals(x))
        assert replay.ended_worse == (after > before + 1e-6), effect
        if effect == "payload":  # the hidden effect: its fit improves on its start
            assert after < before and not replay.ended_worse


def test_a_fit_that_ends_worse_is_reported_failed_not_named(tmp_path, monkeypatch):
    episodes = _record(tmp_path / "s", {"payload": {"mass": 1.5}}, episodes=4)
    # A fit pushed off its optimum at the end (as resetting a component it could not pin
    # down to "no effect" can): at the far bound of the load, the likelihood is worse
    # than at its start.
    fit = identify.least_squares

    def pushed_off(params, residual_fn, **options):
        fitted, result, iterations = fit(params, residual_fn, **options)
        fitted.update_from_vector(params.get_bounds()[1])
        return fitted, result, iterations

    monkeypatch.setattr(identify, "least_squares", pushed_off)
    diagnosis = diagnose(episodes, SCENE, allowed=["payload"])
    payload = diagnosis.candidates[0]
    assert payload.fit_failed and not payload.significant and not diagnosis.selected
    write_markdown(diagnosis, [], tmp_path / "report.md")
    assert "its fit ended worse than it started" in (tmp_path / "report.md").read_text()


def _record_at(path, rate, effects, episodes=2, duration=6.0):
    """Excitation episodes of the pick_place cell logged as a UR controller logs them."""
    scene = _at_rate(rate)
    session = Session.create(path)
    run_excitation(
        "pick_place",
        scene=scene,
        world="plant",
        effects=effects,
        episodes=episodes,
        settings=ExcitationSettings(duration=duration),
        session=session,
    )
    return scene, [read_episode(p, images=False) for p in session.episode_paths()]


def test_a_fit_by_the_likelihoods_bound_improves_where_plain_squares_end_worse(tmp_path):
    """Torque offsets on the shoulder and elbow (a load a payload cannot explain, as on a
    real arm with a tool): a payload fitted by the plain sum of squares trades the wrists'
    torques for the shoulder's and ends with a worse likelihood than it started; the fit
    sees that and fits the likelihood's bound instead, which ends better."""
    offsets = {"torque_offset": {"torque": [0.0, -17.0, -7.0, 0.0, 0.0, 0.0]}}
    scene, episodes = _record_at(tmp_path / "s", 125.0, offsets)
    windows = cut_windows(episodes, compile_scene(scene).layout, [o.name for o in scene.objects])
    plain = WindowReplay(scene, windows, NoiseFloor(), free=["payload"])
    start = likelihood_term(plain.residuals())
    fitted, _, _ = identify.least_squares(
        plain.params, plain.residual_fn, eps=identify.FD_STEP, xtol=identify.XTOL, max_iters=12
    )
    assert likelihood_term(plain.residuals(fitted.as_vector())) > start
    weighed = WindowReplay(scene, windows, NoiseFloor(), free=["payload"])
    x, _, _ = weighed.fit()
    assert likelihood_term(weighed.residuals(x)) < start and not weighed.ended_worse
    assert weighed.refit_by_likelihood
    # The diagnosis's record of the candidate and its report say how it was fitted.
    with Rollout(nthread=2) as pool:
        baseline = score(scene, windows, windows, NoiseFloor(), {}, pool)
        result = fit_candidate(scene, windows, windows, NoiseFloor(), {}, "payload", baseline, pool)
    assert result.by_likelihood and not result.fit_failed
    assert "likelihood's bound" in _verdict(result)


def test_signal_weights_make_the_weighed_squares_one_per_residual():
    residuals = np.random.default_rng(0).normal(0, [1.0, 30.0, 0.2], size=(4, 50, 3))
    weighed = residuals * signal_weights(residuals)
    assert np.mean(weighed**2, axis=(0, 1)) == pytest.approx(np.ones(3))
