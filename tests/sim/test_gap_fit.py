"""A gap fit that ends with a worse likelihood (the one the diagnosis's BIC scores) than
it started with is reported as failed, never named."""

from tests.sim.test_gap_diagnose import SCENE, _record
from twinrl_sim.build import compile_scene
from twinrl_sim.gap import identify
from twinrl_sim.gap.diagnose import diagnose
from twinrl_sim.gap.identify import NoiseFloor, WindowReplay, likelihood_term
from twinrl_sim.gap.report import write_markdown
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
