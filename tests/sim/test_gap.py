"""The gap workflow's replay and localisation on plant data with hidden effects."""

import numpy as np
import pytest

from twinrl_data import schema
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_robot.excitation import run_excitation
from twinrl_sim.gap.identify import _remembering_last_point
from twinrl_sim.gap.inverse import inverse_dynamics_gap
from twinrl_sim.gap.localize import localize
from twinrl_sim.gap.shooting import replay_windows
from twinrl_sim.tasks import make_task

SCENE = make_task("pick_place").scene


def _table(tmp_path, effects):
    session = Session.create(tmp_path / "s")
    paths = run_excitation(
        "pick_place", world="plant", effects=effects, episodes=2, session=session, seed=1
    )
    replays = [replay_windows(read_episode(p), SCENE, window=20) for p in paths]
    return {row.signal: row for row in localize(replays)}


def test_no_effect_leaves_only_sensor_noise(tmp_path):
    rows = _table(tmp_path, {})
    assert max(rows[f"tcp.{a}"].rms for a in "xyz") < 6e-4  # plant TCP noise is 3e-4 m
    assert max(r.rms for n, r in rows.items() if n.startswith("q.")) < 5e-4
    assert all(abs(r.lag_s) < 0.005 for r in rows.values() if not r.signal.startswith("tau"))
    torques = [r for n, r in rows.items() if n.startswith("tau_id.")]
    assert len(torques) == 6 and max(abs(r.bias) for r in torques) < 0.3  # N m


def test_delay_shows_as_lag(tmp_path):
    rows = _table(tmp_path, {"actuator_delay": {"seconds": 0.05}})
    joints = [r for n, r in rows.items() if n.startswith("q.")]
    assert np.median([r.lag_s for r in joints]) > 0.01
    assert max(r.rms for r in joints) > 0.005


def test_payload_shows_as_sag_and_joint_offset_as_tcp_bias(tmp_path):
    payload = _table(tmp_path / "p", {"payload": {"mass": 2.0}})
    assert payload["tcp.z"].bias < -0.001  # the arm sags under the unmodelled load
    assert (
        set(payload["tcp.z"].regimes)
        <= {
            "near_zero_velocity",
            "reversal",
            "high_acceleration",
            "static_hold",
            "free_motion",
            "grasp_transport",
        }
        and payload["tcp.z"].regimes["free_motion"] > 0.001
    )
    # Inverse dynamics: the measured torques carry the load the twin lacks, under gravity.
    assert payload["tau_id.shoulder_lift"].bias < -4 and payload["tau_id.elbow"].bias < -4
    offset = _table(tmp_path / "o", {"joint_offset": {"radians": [0, 0.02, 0, 0, 0, 0]}})
    assert abs(offset["tcp.z"].bias) > 0.005  # the TCP is elsewhere ...
    assert offset["q.shoulder_lift"].rms < 5e-4  # ... while the encoders agree


def test_replay_refuses_a_rate_the_twin_cannot_step(tmp_path):
    session = Session.create(tmp_path / "s")
    path = run_excitation("pick_place", world="twin", episodes=1, session=session)[0]
    episode = read_episode(path)
    episode.meta = episode.meta.replace(fps=7.0)
    with pytest.raises(ValueError, match="not a whole number"):
        replay_windows(episode, SCENE)


def test_localize_cli_writes_table_and_plot(tmp_path):
    import json

    from tests.test_cli import twinrl

    session = Session.create(tmp_path / "s")
    run_excitation("pick_place", world="plant", episodes=1, session=session, seed=2)
    out = tmp_path / "loc"
    result = twinrl(
        "gap", "localize", str(tmp_path / "s"), "--twin", "pick_place", "--out", str(out)
    )
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "localization.json").read_text())
    signals = {r["signal"] for r in report["rows"]}
    assert report["episodes"] == 1 and signals >= {"tcp.z", "q.elbow", "tau_id.elbow"}
    assert (out / "localization.png").stat().st_size > 10_000
    bad = twinrl(
        "gap", "localize", str(tmp_path / "s"), "--twin", "pick_plac", "--out", str(tmp_path / "x")
    )
    assert bad.returncode == 2 and "did you mean 'pick_place'" in bad.stderr
    assert not (tmp_path / "x").exists()


def test_inverse_dynamics_of_a_twin_with_the_load_matches_the_torques(tmp_path):
    session = Session.create(tmp_path / "s")
    paths = run_excitation(
        "pick_place",
        world="plant",
        effects={"payload": {"mass": 2.0}},
        episodes=1,
        session=session,
        seed=1,
    )
    episode = read_episode(paths[0])
    before = inverse_dynamics_gap([episode], SCENE)
    after = inverse_dynamics_gap([episode], SCENE, {"payload": {"mass": 2.0}})
    for joint in ("shoulder_lift", "elbow", "wrist_1"):
        assert after[f"tau_id.{joint}"] < 0.8 * before[f"tau_id.{joint}"]
    untorqued = {k: v for k, v in episode.data.items() if k != schema.EFFORT}
    without_torques = schema.Episode(meta=episode.meta, data=untorqued)
    assert inverse_dynamics_gap([without_torques], SCENE) == {}


def test_a_large_gap_nothing_explains_is_reported_as_far_off_and_where() -> None:
    from twinrl_sim.gap.localize import Disagreement
    from twinrl_sim.gap.report import verdict

    rows = [
        Disagreement("tcp.z", "m", 0.09, 0.09, 1.0, 0.0, {"moving": 0.09, "still": 0.08}),
        Disagreement("q.elbow", "rad", 0.01, 0.0, 0.9, 0.03, {"moving": 0.02}),
    ]
    far = verdict(412.0, 412.0, False, rows)
    assert "far off" in far and "no candidate explains it" in far
    assert "`tcp.z`" in far and "the TCP frame" in far and "worst when moving" in far
    assert "far off" in verdict(300.0, 40.0, True, rows)
    assert "explains the held-out data" in verdict(30.0, 1.1, True, rows)
    assert "Close, not exact" in verdict(30.0, 1.8, True, rows)


def _at_rate(rate: float):
    """The pick_place cell logged as a UR controller logs: at ``rate``, tracking servos."""
    physics = SCENE.physics.model_copy(update={"control_hz": rate, "servo": "track"})
    return SCENE.model_copy(update={"physics": physics})


def test_a_window_is_two_seconds_of_the_log_at_any_rate(tmp_path):
    from twinrl_robot.excitation import ExcitationSettings
    from twinrl_sim.build import compile_scene
    from twinrl_sim.gap.windows import cut_windows

    for rate, rows in ((10.0, 20), (125.0, 250)):
        scene = _at_rate(rate)
        session = Session.create(tmp_path / f"s{rate:g}")
        (path,) = run_excitation(
            "pick_place",
            scene=scene,
            world="twin",
            episodes=1,
            settings=ExcitationSettings(duration=6.0),
            session=session,
        )
        episode = read_episode(path, images=False)
        layout = compile_scene(scene).layout
        windows = cut_windows([episode], layout, [])
        assert windows.measured.shape[1] == rows and len(windows) == (len(episode) - 1) // rows
        assert cut_windows([episode], layout, [], window=7).measured.shape[1] == 7  # as given


@pytest.mark.long  # beyond CI's time (make test-long)
@pytest.mark.slow  # six 10 s episodes at 125 Hz, three candidates on 2 s windows: ~2 min
def test_a_125_hz_log_names_its_delay_and_payload_not_a_servo_gain(tmp_path):
    """At 125 Hz, windows of 20 rows (0.16 s) took a hidden delay and payload for a
    softer servo gain; windows of 2 s tell them apart."""
    from twinrl_robot.excitation import ExcitationSettings
    from twinrl_sim.gap.diagnose import diagnose

    scene = _at_rate(125.0)
    session = Session.create(tmp_path / "s")
    hidden = {"actuator_delay": {"seconds": 0.03}, "payload": {"mass": 2.0}}
    run_excitation(
        "pick_place",
        scene=scene,
        world="plant",
        effects=hidden,
        episodes=6,
        settings=ExcitationSettings(duration=10.0),
        session=session,
    )
    episodes = [read_episode(p, images=False) for p in session.episode_paths()]
    allowed = ["actuator_delay", "servo_gain", "payload"]
    diagnosis = diagnose(episodes, scene, allowed=allowed)
    assert sorted(s["effect"] for s in diagnosis.selected) == ["actuator_delay", "payload"]
    assert diagnosis.effects["actuator_delay"]["seconds"] == pytest.approx(0.03, rel=0.15)
    assert diagnosis.effects["payload"]["mass"] == pytest.approx(2.0, rel=0.15)


def test_a_fit_does_not_replay_its_last_point_again():
    """The optimiser's last point is asked for again (intervals, information criteria):
    answered from memory, while new points and finite-difference batches are replayed."""
    calls = []

    def residual_fn(x, params, **kwargs):
        calls.append(np.shape(x))
        return [np.atleast_2d(x).sum(axis=0)], [], []

    remembering = _remembering_last_point(residual_fn)
    first = remembering(np.array([[1.0], [2.0]]), None)  # as the optimiser asks: a column
    again = remembering(np.array([1.0, 2.0]), "another template")
    assert first[0][0].shape == (1, 1) and again[0][0].shape == (1,)
    assert again[0][0][0] == first[0][0][0, 0]
    remembering(np.array([[1.0, 1.1], [2.0, 2.0]]), None)  # a batch: always replayed
    remembering(np.array([1.0, 2.5]), None)
    remembering(np.array([1.0, 2.0]), None)  # no longer the last point alone
    assert calls == [(2, 1), (2, 2), (2,), (2,)]
