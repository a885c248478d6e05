"""Near misses, the hard negatives a reward classifier learns from: the scripted expert
stopping short near the goal in every task; and a classifier judged on episodes it never
saw, per frame and per episode (`twinrl judge`)."""

import json
import shutil

import numpy as np
import pytest

from tests.test_cli import twinrl as run_cli
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn import reward_check
from twinrl_learn.errors import LearnError
from twinrl_learn.reward_check import NEAR_MISS_POLICY, check_reward_classifier
from twinrl_learn.reward_classifier import (
    ClassifierSettings,
    RewardClassifier,
    episodes_under,
    train_reward_classifier,
)
from twinrl_robot.errors import RobotError
from twinrl_robot.scripted import NEAR_MISS_HOLD, run_scripted_expert
from twinrl_sim.tasks import TASKS, make_task
from twinrl_sim.tasks.expert import stopping_short


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Plant pick-and-place episodes: 2 that succeed and go on 3 steps, 2 near misses."""
    session = Session.create(tmp_path_factory.mktemp("near") / "session")
    for share in (0.0, 1.0):
        run_scripted_expert("pick_place", world="plant", episodes=2, regions=("ID",), seed=6,
                            session=session, settle=3, near_misses=share)  # fmt: skip
    return session.path


@pytest.fixture(scope="module")
def classifier(session, tmp_path_factory):
    """A classifier's folder (a few steps: what it judges matters less than the counts)."""
    out = tmp_path_factory.mktemp("judge") / "success"
    settings = ClassifierSettings(image_size=32, steps=20, heldout=0.5)
    train_reward_classifier(episodes_under([session], ("front",)), out, settings)
    return out


@pytest.mark.parametrize("task", TASKS)
def test_a_near_miss_stops_short_of_success_near_the_goal(task):
    report = run_scripted_expert(task, episodes=1, regions=("ID",), seed=4, near_misses=1.0)
    (episode,) = report.episodes
    assert episode.near_miss and not episode.success
    assert episode.steps < make_task(task).max_steps  # it ended once held, not timed out
    (plain,) = run_scripted_expert(task, episodes=1, regions=("ID",), seed=4).episodes
    assert plain.success and not plain.near_miss


def test_a_near_miss_holds_the_object_over_its_goal_and_is_recorded_as_one(session):
    episodes = [read_episode(p) for p in sorted(session.glob("**/*.mcap"))]
    near = [e for e in episodes if e.meta.policy == NEAR_MISS_POLICY]
    assert len(near) == 2 and all(e.meta.success is False for e in near)
    names = near[0].meta.names["observation.environment_state"]
    banana, plate = names.index("banana.x"), names.index("plate.x")
    for episode in near:
        last = np.asarray(episode.data["observation.environment_state"])[-1]
        lateral = np.linalg.norm(last[banana : banana + 2] - last[plate : plate + 2])
        above = last[banana + 2] - last[plate + 2]
        assert lateral < 0.03 and 0.02 < above < 0.07  # held over the plate, not on it
        held = np.asarray(episode.data["action"])[-NEAR_MISS_HOLD:]
        assert np.allclose(held[:, :6], 0.0) and np.all(held[:, 6] == 1.0)  # still, holding


def test_near_misses_refuse_a_bad_share_or_phase(tmp_path):
    with pytest.raises(RobotError, match=r"near_misses is a share of the episodes in \[0, 1\]"):
        run_scripted_expert("pick_place", episodes=1, near_misses=1.5)
    task = make_task("pick_place")
    expert = task.expert(task.sample_config(np.random.default_rng(0), "ID"),
                         np.random.default_rng(0))  # fmt: skip
    with pytest.raises(ValueError, match="no phase 'insert'; its phases: approach"):
        stopping_short(expert, "insert", 0.5)
    with pytest.raises(ValueError, match=r"fraction in \[0, 1\)"):
        stopping_short(expert, "lower", 1.0)
    result = run_cli("sim", "expert", "pick_place", "--episodes", "1", "--near-misses", "2")
    assert result.returncode != 0 and "near-misses" in result.stderr


def test_a_classifier_is_judged_per_frame_and_per_episode(session, classifier):
    episodes = episodes_under([session], ("front",))
    judge = RewardClassifier.load(classifier)
    check = check_reward_classifier(judge, episodes)
    assert check.successful_episodes == 2 and check.failed_episodes == 2
    assert check.near_miss_episodes == 2 and check.frames > check.positives == 2 * 3
    judge.threshold = -1.0  # says success everywhere
    always = check_reward_classifier(judge, episodes)
    assert always.false_successes == always.near_miss_false_successes == 2
    assert always.missed_successes == 0 and always.recall == 1.0
    assert always.precision == pytest.approx(6 / always.frames)
    assert (always.episode_precision, always.episode_recall) == (0.5, 1.0)  # 2 of 4 rewarded
    judge.threshold = 2.0  # never
    never = check_reward_classifier(judge, episodes)
    assert never.false_successes == 0 and never.missed_successes == 2 and never.recall == 0.0
    assert (never.episode_precision, never.episode_recall) == (0.0, 0.0)
    judge.task = "insert_hexagon"
    with pytest.raises(LearnError, match="judges insert_hexagon, and some episodes are of pick"):
        check_reward_classifier(judge, episodes)


def test_an_episodes_success_can_need_successive_frames(session, classifier, monkeypatch):
    """As real RL's --success-frames: every other frame called a success is a false
    success when one frame makes a success, and none when two must follow each other."""
    episodes = episodes_under([session], ("front",))
    judge = RewardClassifier.load(classifier)
    monkeypatch.setattr(
        reward_check, "predict", lambda net, images, gripper: np.arange(len(images)) % 2
    )
    one = check_reward_classifier(judge, episodes)
    assert one.success_frames == 1 and one.false_successes == 2 and one.missed_successes == 0
    two = check_reward_classifier(judge, episodes, success_frames=2)
    assert two.success_frames == 2 and two.false_successes == 0 and two.missed_successes == 2
    assert (two.precision, two.recall) == (one.precision, one.recall)  # frames as before
    # Frames either side of a gap in the steps (the frames left out before a success)
    # do not follow each other.
    assert reward_check._longest_run(np.array([1, 2, 4, 5, 6]), np.ones(5, bool)) == 3
    assert reward_check._longest_run(np.array([1, 2, 3]), np.array([True, False, True])) == 1
    with pytest.raises(LearnError, match="at least 1 frame"):
        check_reward_classifier(judge, episodes, success_frames=0)


def test_the_judge_command_prints_and_writes_the_scores(session, classifier, tmp_path):
    out = tmp_path / "check.json"
    result = run_cli("judge", str(classifier), str(session), "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "false successes:" in result.stdout and "of 2 near misses" in result.stdout
    three = run_cli("judge", str(classifier), str(session), "--success-frames", "3")
    assert three.returncode == 0 and "(3 successive frames make one)" in three.stdout
    # A classifier whose settings this version cannot read is said in one line.
    foreign = tmp_path / "foreign"
    shutil.copytree(classifier, foreign)
    saved = json.loads((foreign / "classifier.json").read_text())
    (foreign / "classifier.json").write_text(json.dumps({**saved, "unknown_setting": 1}))
    refused = run_cli("judge", str(foreign), str(session))
    assert refused.returncode != 0 and "cannot read" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    saved = json.loads(out.read_text())
    assert saved["near_miss_episodes"] == 2 and 0.0 <= saved["episode_precision"] <= 1.0
    assert "per episode precision" in result.stdout
    again = run_cli("judge", str(classifier), str(session), "--out", str(out))
    assert again.returncode == 2 and "exists" in again.stderr
    assert len(again.stderr.strip().splitlines()) == 1
