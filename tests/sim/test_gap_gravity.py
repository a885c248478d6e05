"""The arm's gravity model from its joint torques: servos that feed the model forward log
a tool's weight where a UR logs it, the gravity parameters the torques cannot tell apart
are left at the nominal model (and said so), and a hidden tool with an off-axis centre of
gravity and a wrong upper-arm and forearm mass are named from a UR-rate log."""

import numpy as np
import pytest
from mujoco.rollout import Rollout

from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_robot.excitation import ExcitationSettings, run_excitation
from twinrl_sim.build import build_mjspec, compile_scene
from twinrl_sim.gap.diagnose import candidate_pool, diagnose
from twinrl_sim.gap.gravity import separable_parts
from twinrl_sim.gap.identify import WindowReplay
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.gap.windows import cut_windows
from twinrl_sim.tasks import make_task

TOOL = {"mass": 2.2, "cog": [0.04, -0.03, 0.08]}  # kg, m in the flange frame
ARM_ERROR = [1.0, 1.07, 0.93, 1.0, 1.0, 1.0]  # upper arm 7 % heavier, forearm 7 % lighter
HIDDEN = {"payload": TOOL, "link_mass": {"scale": ARM_ERROR}}


def _ur_twin(rate: float):
    """pick_place's cell as a UR controller runs and logs it: tracking servos that feed
    the arm's model forward, at ``rate``."""
    scene = make_task("pick_place").scene
    physics = scene.physics.model_copy(update={"control_hz": rate, "servo": "track"})
    return scene.model_copy(update={"physics": physics})


def _logs(tmp_path, rate: float, episodes: int, duration: float, hidden=HIDDEN) -> list:
    session = Session.create(tmp_path / f"logs{rate:g}")
    run_excitation(
        "pick_place",
        scene=_ur_twin(rate),
        world="plant",
        effects=hidden,
        episodes=episodes,
        settings=ExcitationSettings(duration=duration),
        session=session,
        seed=2,
    )
    return [read_episode(p, images=False) for p in session.episode_paths()]


def test_only_the_gravity_parameters_torques_can_separate_are_fitted():
    spec, layout = build_mjspec(_ur_twin(125.0))
    parts = separable_parts(spec, spec.compile(), layout)
    # The upper arm and the forearm carry the arm's reach; the base link turns about the
    # vertical and two wrist links weigh where a payload does.
    assert parts.link_mass == (1, 2)
    assert parts.lumped["link_mass.shoulder_pan"] == "never loads a joint against gravity"
    assert "payload" in parts.lumped["link_mass.wrist_3"]
    assert parts.link_com == ()  # a centre of mass along a link acts as its mass does


def test_the_tool_and_the_arm_masses_are_fitted_together_from_torques(tmp_path):
    episodes = _logs(tmp_path, 125.0, episodes=4, duration=8.0)
    scene = _ur_twin(125.0)
    windows = cut_windows(episodes, compile_scene(scene).layout, [])
    pool, skipped = candidate_pool(windows, ["payload", "link_mass", "link_com"], scene)
    assert pool == ["payload", "link_mass"] and "link_com" in skipped
    assert "link_mass.wrist_2" in skipped  # said in the report's "Not fitted"
    replay = WindowReplay(scene, windows, NoiseFloor(), free=["payload", "link_mass"])
    x, half_width, _ = replay.fit()
    fitted, interval = replay.effects_at(x), replay.intervals_at(half_width)
    assert fitted["payload"]["mass"] == pytest.approx(TOOL["mass"], rel=0.02)
    assert fitted["payload"]["cog"] == pytest.approx(TOOL["cog"], abs=0.002)
    scale = np.array(fitted["link_mass"]["scale"])
    assert scale[1:3] - 1 == pytest.approx(np.array(ARM_ERROR[1:3]) - 1, rel=0.1)
    assert scale[[0, 3, 4, 5]] == pytest.approx(1.0)  # not fitted: the nominal model
    assert np.isinf(np.array(interval["link_mass"]["scale"])[[0, 3, 4, 5]]).all()


@pytest.mark.long  # beyond CI's time (make test-long)
@pytest.mark.slow  # four 8 s episodes and a diagnosis at each UR rate: ~2 min each
@pytest.mark.parametrize("rate", [125.0, 500.0], ids=["CB3 125 Hz", "e-Series 500 Hz"])
def test_a_hidden_tool_and_gravity_error_are_named_at_ur_rates(tmp_path, rate):
    episodes = _logs(tmp_path, rate, episodes=4, duration=8.0)
    allowed = ["payload", "link_mass", "link_com", "torque_offset", "actuator_delay"]
    diagnosis = diagnose(episodes, _ur_twin(rate), allowed=allowed)
    assert [s["effect"] for s in diagnosis.selected] == ["payload", "link_mass"]
    named = diagnosis.effects
    assert named["payload"]["mass"] == pytest.approx(TOOL["mass"], rel=0.1)
    cog = np.array(named["payload"]["cog"])
    assert np.abs(cog - TOOL["cog"]).max() < 0.1 * np.linalg.norm(TOOL["cog"])
    error = np.array(named["link_mass"]["scale"]) - 1
    assert error[1:3] == pytest.approx(np.array(ARM_ERROR[1:3]) - 1, rel=0.1)
    assert diagnosis.heldout_reduction >= 0.7


def test_an_effect_that_others_explain_once_named_is_dropped(tmp_path):
    """A constant torque offset stands in for a tool's weight over a few poses; once the
    payload is named beside it, the payload alone explains the log and the offset goes."""
    from twinrl_sim.gap.diagnose import split_windows
    from twinrl_sim.gap.search import prune

    episodes = _logs(tmp_path, 125.0, episodes=3, duration=6.0, hidden={"payload": TOOL})
    scene = _ur_twin(125.0)
    windows = cut_windows(episodes, compile_scene(scene).layout, [])
    split = split_windows(episodes, windows, 0.3, 0)
    offset = WindowReplay(scene, split.train, NoiseFloor(), free=["torque_offset"])
    x, _, _ = offset.fit()
    named = [{"effect": "torque_offset", "params": offset.effects_at(x)["torque_offset"]}]
    both = WindowReplay(
        scene, split.train, NoiseFloor(), free=["torque_offset", "payload"],
        start={"torque_offset": named[0]["params"]},
    )  # fmt: skip
    x, _, _ = both.fit()
    fitted = both.effects_at(x)
    named += [{"effect": "payload", "params": fitted["payload"]}]
    named[0]["params"] = fitted["torque_offset"]
    with Rollout(nthread=2) as pool:
        _, kept, dropped = prune(scene, split.train, split.held, NoiseFloor(), named, pool)
    assert [k["effect"] for k in kept] == ["payload"] and "torque_offset" in dropped
