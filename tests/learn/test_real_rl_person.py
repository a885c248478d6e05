"""Real RL with a person: the scripted person at a virtual device takes over and hands
back, the reward classifier or the person's key judges success, a pause keeps
everything for resume; on the emulated UR arm end to end."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rerun.experimental import RrdReader

from tests.conftest import tiny_state_policy
from tests.learn.test_real_rl import real_settings as stage3_settings
from tests.robot.test_ur_cell import write_cell
from tests.test_cli import twinrl as run_cli
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.errors import LearnError
from twinrl_learn.real_rl import RealRL
from twinrl_learn.real_rl_progress import load_evaluations
from twinrl_learn.reward_classifier import (
    ClassifierSettings,
    RewardClassifier,
    episodes_under,
    labelled_frames,
    train_reward_classifier,
)
from twinrl_robot.person_in_loop import PersonInLoop
from twinrl_robot.scripted import run_scripted_expert
from twinrl_robot.ur.emulator.harness import EmulatorProcess


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return tiny_state_policy(tmp_path_factory.mktemp("person"), seed=5, steps=20)


@pytest.fixture(scope="module")
def plant_episodes(tmp_path_factory):
    """Expert episodes in the plant that go on 3 steps after each success, and failures."""
    folder = tmp_path_factory.mktemp("settled")
    session = Session.create(folder / "session")
    for episodes, noise in ((3, 0.002), (1, 0.01)):  # a shaky hand fails
        run_scripted_expert(
            "pick_place", world="plant", episodes=episodes, seed=2, session=session, settle=3,
            action_noise=noise,
        )  # fmt: skip
    return folder / "session"


@pytest.fixture(scope="module")
def classifier(plant_episodes, tmp_path_factory):
    out = tmp_path_factory.mktemp("classifier") / "success"
    settings = ClassifierSettings(image_size=32, steps=150)
    report = train_reward_classifier(episodes_under([plant_episodes], ("front",)), out, settings)
    assert report.heldout_episodes == 2 and report.fitted_episodes == 6
    return out


def real_settings(demos, out, **overrides):
    """Stage III's test settings, shorter and without the reset renders."""
    return stage3_settings(demos, out, **({"plant_steps": 40, "show_resets": False} | overrides))


def test_success_frames_are_those_recorded_after_the_succeeding_step(plant_episodes):
    episodes = episodes_under([plant_episodes], ("front",))
    frames = labelled_frames(episodes, ClassifierSettings(margin=4))
    for index, episode in enumerate(episodes):
        rows = frames.episode == index
        succeeded = np.flatnonzero(episode.data["next.success"])
        if episode.meta.success:
            first = succeeded[0]
            assert list(frames.step[rows & frames.labels]) == list(range(first + 1, len(episode)))
            left_out = set(range(first - 4, first + 1))
            assert not left_out & set(frames.step[rows])
        else:
            assert not frames.labels[rows].any() and rows.sum() == len(episode)
    assert any(e.meta.success for e in episodes) and not all(e.meta.success for e in episodes)


def test_the_classifier_refuses_what_it_cannot_learn_from(plant_episodes, tmp_path):
    episodes = episodes_under([plant_episodes], ("front",))
    with pytest.raises(LearnError, match="no camera top"):
        labelled_frames(episodes, ClassifierSettings(cameras=("top",)))
    unsettled = Session.create(tmp_path / "unsettled")
    run_scripted_expert("pick_place", world="plant", episodes=1, seed=3, session=unsettled)
    with pytest.raises(LearnError, match="no frame shows a success.*`settle`"):
        labelled_frames(episodes_under([unsettled.path], ("front",)), ClassifierSettings())
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "x").write_text("")
    with pytest.raises(LearnError, match="exists and is not empty"):
        train_reward_classifier(episodes, tmp_path / "taken")
    result = run_cli("train", "reward-classifier", str(plant_episodes), "--task", "insert_hexagon",
                     "--out", str(tmp_path / "none"))  # fmt: skip
    assert result.returncode != 0 and "no episode of insert_hexagon" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "none").exists()


def test_the_classifier_command_writes_a_report_with_its_mistakes(plant_episodes, tmp_path):
    out = tmp_path / "success"
    result = run_cli(
        "train", "reward-classifier", str(plant_episodes), "--camera", "front",
        "--out", str(out), "--steps", "60", "--image-size", "32",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["heldout_episodes"] >= 1 and 0.0 <= metrics["accuracy"] <= 1.0
    assert "![mistakes](mistakes.png)" in (out / "report.md").read_text()
    assert (out / "mistakes.png").stat().st_size > 1000
    classifier = RewardClassifier.load(out)
    assert classifier.task == "pick_place" and classifier.settings.image_size == 32


def test_a_classifier_on_the_pretrained_encoder_trains_saves_and_judges(plant_episodes, tmp_path):
    out = tmp_path / "pretrained"
    result = run_cli(
        "train", "reward-classifier", str(plant_episodes), "--camera", "front",
        "--camera", "wrist", "--encoder", "pretrained", "--out", str(out), "--steps", "40",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "frozen ImageNet-pretrained encoder" in (out / "report.md").read_text()
    classifier = RewardClassifier.load(out)
    assert classifier.settings.encoder == "pretrained"
    # Only the trained head is saved: the backbone comes from its package.
    assert (out / "weights.safetensors").stat().st_size < 2_000_000
    episode = episodes_under([plant_episodes], ("front", "wrist"))[0]
    observation = {
        "observation.state": episode.data["observation.state"][-1],
        **{f"observation.images.{c}": episode.images[c][-1] for c in ("front", "wrist")},
    }
    assert 0.0 <= classifier.probability(observation) <= 1.0
    bad = run_cli("train", "reward-classifier", str(plant_episodes), "--encoder", "dino",
                  "--out", str(tmp_path / "bad"))  # fmt: skip
    assert bad.returncode != 0 and "--encoder must be one of scratch, pretrained" in bad.stderr
    assert not (tmp_path / "bad").exists()


def test_the_classifier_judges_real_rl_and_a_pause_keeps_the_run(demos, classifier, tmp_path):
    # A classifier that sees success everywhere ends every episode after its first step:
    # the episode's outcome is the classifier's, not the plant's ground truth.
    eager = tmp_path / "eager"
    eager.mkdir()
    for name in ("weights.safetensors", "classifier.json"):
        (eager / name).write_bytes((classifier / name).read_bytes())
    settings = json.loads((eager / "classifier.json").read_text())
    (eager / "classifier.json").write_text(json.dumps(settings | {"threshold": 0.0}))
    out = tmp_path / "run"
    real = RealRL.start(
        real_settings(demos, out, success="classifier", classifier=str(eager), plant_steps=6)
    )
    assert real.person is None  # the plant: nobody at the keys, the simulated operator
    paused = []

    def pause_after_three(record, run):
        if len(run.run_state.history) == 3:  # the person presses q (their pause key)
            run.person = PersonInLoop(None, None, sets_up=False)
            run.person.marks.add(["quit"])
            paused.append(True)

    run = real.run(on_episode=pause_after_three)
    assert paused and real.paused and len(run.history) == 3 and run.agent.env_steps == 3
    episodes = [read_episode(p, images=False) for p in Session(out / "session").episode_paths()]
    assert all(len(e) == 1 and e.meta.success for e in episodes)
    resumed = RealRL.resume(
        real_settings(demos, out, success="classifier", classifier=str(eager), plant_steps=6)
    )
    resumed.run()
    assert resumed.run_state.agent.env_steps == 6 and len(resumed.run_state.history) == 6
    assert load_evaluations(out)[-1].plant_steps == 6
    # Asked for 3 successive frames, the same classifier ends each episode at its third.
    out = tmp_path / "debounced"
    debounced = real_settings(
        demos, out, success="classifier", classifier=str(eager), plant_steps=6, success_frames=3
    )
    RealRL.start(debounced).run()
    episodes = [read_episode(p, images=False) for p in Session(out / "session").episode_paths()]
    assert [len(e) for e in episodes] == [3, 3] and all(e.meta.success for e in episodes)


def test_the_persons_success_key_ends_an_episode_in_the_plant(demos, tmp_path):
    real = RealRL.start(
        real_settings(demos, tmp_path / "run", teleop="scripted", success="key", plant_steps=150)
    )
    assert real.person is not None and real.person.operator is not None
    run = real.run()
    episodes = [
        read_episode(p, images=False) for p in Session(tmp_path / "run" / "session").episode_paths()
    ]
    assert all(e.meta.operator == "scripted" for e in episodes)
    helped = [e for e in episodes if e.meta.num_interventions]
    assert helped, "the scripted person never took over an untrained policy"
    won = [e for e in episodes if e.meta.success]
    assert won, "the scripted person finished no episode it took over"
    assert len(run.demo.episodes) >= len(helped)


def test_real_rl_settings_refuse_what_a_cell_cannot_do(demos, classifier, tmp_path):
    with pytest.raises(ValueError, match="cell a UR arm needs its cell file"):
        real_settings(demos, tmp_path / "a", robot="ur")
    with pytest.raises(ValueError, match="success truth needs ground truth"):
        real_settings(demos, tmp_path / "a", robot="ur", cell="cell.yaml")
    with pytest.raises(ValueError, match="classifier is needed to judge success"):
        real_settings(demos, tmp_path / "a", success="classifier")
    with pytest.raises(ValueError, match="success_frames is read only when"):
        real_settings(demos, tmp_path / "a", success_frames=3)
    with pytest.raises(ValueError, match="success_frames must be at least 1, got 0"):
        real_settings(demos, tmp_path / "a", success="classifier", classifier="c", success_frames=0)
    other = tmp_path / "other"
    other.mkdir()
    for name in ("weights.safetensors", "classifier.json"):
        (other / name).write_bytes((classifier / name).read_bytes())
    settings = json.loads((other / "classifier.json").read_text())
    (other / "classifier.json").write_text(json.dumps(settings | {"task": "insert_hexagon"}))
    with pytest.raises(ValueError, match="judges insert_hexagon, not pick_place"):
        RealRL.start(
            real_settings(demos, tmp_path / "b", success="classifier", classifier=str(other))
        )
    assert not (tmp_path / "b").exists()
    result = run_cli(
        "train", "real-rl", "--task", "pick_place", "--out", str(tmp_path / "c"),
        "--init", str(demos[1]), "--success", "key",
    )  # fmt: skip
    assert result.returncode != 0 and "key needs the person's keys" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "c").exists()


@pytest.mark.realtime  # the emulated arm keeps real time: ~10 s an episode
def test_a_scripted_person_and_the_classifier_run_real_rl_on_the_emulated_arm(
    demos, classifier, tmp_path: Path
):
    cell = write_cell(tmp_path)
    data = yaml.safe_load(cell.read_text())
    url = f"http://{data['arm']['host']}:8080/front"
    data["cameras"] = [{"name": "front", "source": url, "width": 64, "height": 48, "fps": 15}]
    cell.write_text(yaml.safe_dump(data))
    out = tmp_path / "run"
    settings = real_settings(
        demos, out, robot="ur", cell=str(cell), emulated=True, teleop="scripted",
        success="classifier", classifier=str(classifier), plant_steps=60, show_resets=True,
    )  # fmt: skip
    with EmulatorProcess(cell, effects=None):
        run = RealRL.start(settings).run()
    # The live view: each reset rendered from the cell's twin, its outlines over the live
    # camera, and the episode's signals.
    shown = RrdReader(out / "live-00000.rrd").store().schema().entity_paths()
    for entity in ("/guidance/front/outline", "/cameras/front", "/cameras/front/target"):
        assert entity in shown, entity
    assert "/signals/intervention" in shown
    episodes = [read_episode(p) for p in Session(out / "session").episode_paths()]
    assert len(episodes) >= 1 and sum(len(e) for e in episodes) == run.agent.env_steps >= 60
    for episode in episodes:
        assert (episode.meta.world, episode.meta.operator) == ("real", "scripted")
        assert episode.images["front"].shape[1:] == (48, 64, 3)
        flags = episode.data["intervention"]
        assert int(flags.sum()) == episode.meta.num_interventions
    assert any(e.meta.num_interventions for e in episodes), "the person never took over"
    points = load_evaluations(out)  # a UR cell: the run's own episodes, no plant grid
    assert points[-1].episodes == 0 and points[-1].plant_steps == run.agent.env_steps
