"""Real RL's actor–learner split: the learner in a process of its own, killed mid-run."""

import json
import os
import shutil
import signal

import pytest

from tests.conftest import tiny_state_policy
from twinrl_data.errors import SettingError
from twinrl_data.session import Session
from twinrl_learn.agent import Agent
from twinrl_learn.real_rl import RealRL
from twinrl_learn.remote_learner import RemoteLearner
from twinrl_learn.settings import RealRLSettings, RLConfig


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return tiny_state_policy(tmp_path_factory.mktemp("split"), seed=4, steps=20)


def _settings(demos, out, **changes) -> RealRLSettings:
    dataset, sft = demos
    fields = dict(
        task="pick_place", init=str(sft), out=str(out), demos=[str(dataset)],
        plant_steps=400, eval_every=0, eval_grid=(1, 1), refresh_every=0, show_resets=False,
        operator=None, learner="process",
        rl=RLConfig.for_method("twinrl", offline_steps=3, batch_size=16, seed=2),
    )  # fmt: skip
    return RealRLSettings(**(fields | changes))


def test_a_killed_learner_loses_no_episode_and_the_robot_never_stops(demos, tmp_path):
    said = []
    real = RealRL.start(_settings(demos, tmp_path / "run"), on_notice=said.append)
    updates_seen = []

    def on_episode(record, real: RealRL) -> None:
        updates_seen.append(real.run_state.agent.updates)
        if len(real.run_state.history) == 2:  # the learner dies after the second episode
            assert isinstance(real.learner, RemoteLearner)
            os.kill(real.learner.learner_pid(), signal.SIGKILL)

    run = real.run(on_episode=on_episode)
    episodes = Session(tmp_path / "run" / "session").episode_paths()
    assert len(episodes) == len(run.history) >= 4 and run.agent.env_steps >= 400
    # The learner alone holds the buffers: the actor read no demo and keeps no episode.
    assert len(run.demo) == len(run.online) == 0
    # The robot went on: the third episode was acted with the weights of before.
    assert any("the learner is lost" in m for m in said)
    assert any("a learner is back" in m for m in said)
    assert updates_seen[2] == updates_seen[1]
    # The learner that came back holds every episode, in order, and was granted every
    # robot step: its updates went on from its checkpoint.
    learner = tmp_path / "run" / "learner"
    assert [p.name for p in Session(learner / "session").episode_paths()] == [
        p.name for p in episodes
    ]
    state = json.loads((learner / "run.json").read_text())
    assert state["episodes_logged"] == len(episodes)
    assert updates_seen[-1] > updates_seen[2]
    assert run.agent.updates == updates_seen[-1]


def test_a_learner_that_cannot_start_again_is_tried_after_each_episode(demos, tmp_path):
    """A learner whose restart fails (here its checkpoint is unreadable) is said and tried
    again after the next episode; the robot goes on, and once the folder is gone a
    learner starts from the actor's weights and is sent every episode."""
    said = []
    real = RealRL.start(_settings(demos, tmp_path / "run", plant_steps=700), on_notice=said.append)
    learner = tmp_path / "run" / "learner"

    def on_episode(record, real: RealRL) -> None:
        episodes = len(real.run_state.history)
        if episodes == 2:  # killed, and its checkpoint spoilt: it cannot resume
            assert isinstance(real.learner, RemoteLearner)
            os.kill(real.learner.learner_pid(), signal.SIGKILL)
            (learner / "run.json").write_text("{ not json")
        elif episodes == 4:  # a person clears the folder: the next learner starts anew
            assert any("a learner could not start again" in m for m in said)
            shutil.rmtree(learner)

    run = real.run(on_episode=on_episode)
    failed = [m for m in said if "a learner could not start again" in m]
    assert len(failed) == 1 and "JSONDecodeError" in failed[0]
    assert "trying again after the next episode" in failed[0]
    assert said.index(failed[0]) < max(i for i, m in enumerate(said) if "a learner is back" in m)
    episodes = Session(tmp_path / "run" / "session").episode_paths()
    assert len(episodes) == len(run.history) >= 5 and run.agent.env_steps >= 700
    assert [p.name for p in Session(learner / "session").episode_paths()] == [
        p.name for p in episodes
    ]


def test_a_learner_on_a_new_machine_is_sent_every_episode_when_the_actor_resumes(demos, tmp_path):
    """The learner's folder is gone (another machine): the resumed actor's learner starts
    from the actor's last weights and is sent every episode before the run goes on."""
    first = RealRL.start(_settings(demos, tmp_path / "run", plant_steps=200)).run()
    steps, updates = first.agent.env_steps, first.agent.updates
    shutil.rmtree(tmp_path / "run" / "learner")
    said, seen = [], []
    resumed = RealRL.resume(
        _settings(demos, tmp_path / "run", plant_steps=300), on_notice=said.append
    )
    assert len(resumed.run_state.demo) == len(resumed.run_state.online) == 0  # not read back
    run = resumed.run(on_episode=lambda record, real: seen.append(record.updates))
    actor = [p.name for p in Session(tmp_path / "run" / "session").episode_paths()]
    learner = Session(tmp_path / "run" / "learner" / "session")
    assert len(actor) >= 3 and [p.name for p in learner.episode_paths()] == actor
    # Its counters go on from the actor's: no second offline phase, no step paid twice.
    assert seen and seen[0] > updates and seen == sorted(seen)
    learnt = Agent.load(tmp_path / "run" / "learner" / "agent")
    assert learnt.env_steps == run.agent.env_steps > steps
    assert learnt.updates == run.agent.updates == updates + (run.agent.env_steps - steps)


def test_a_learner_apart_is_named_where_it_runs(demos, tmp_path):
    with pytest.raises(SettingError, match="learner_folder"):
        _settings(demos, tmp_path, learner="", learner_folder=str(tmp_path / "l"))
    with pytest.raises(SettingError, match="learner must be empty .* got 'ray://no port'"):
        _settings(demos, tmp_path, learner="ray://no port")


def test_the_command_refuses_a_learner_it_cannot_reach_in_one_line(demos, tmp_path):
    from tests.test_cli import twinrl as run_cli

    dataset, sft = demos
    out = tmp_path / "run"
    result = run_cli(
        "train", "real-rl", "--task", "pick_place", "--init", str(sft), "--out", str(out),
        "--demos", str(dataset), "--learner", "ray://no port",
    )  # fmt: skip
    assert result.returncode == 2 and "learner must be empty" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not out.exists()


def test_a_second_learner_is_kept_out_of_a_folder_a_learner_holds(demos, tmp_path):
    """Two learners on one folder would write one run's checkpoints over each other: a
    second run's learner is refused, naming the holder, until the first is gone."""
    from twinrl_data.actors import ProcessActors
    from twinrl_learn.errors import LearnError
    from twinrl_learn.real_rl import learner_spec
    from twinrl_learn.remote_learner import LearnerService

    folder = str(tmp_path / "shared_learner")
    first = RealRL.start(_settings(demos, tmp_path / "a", learner_folder=folder))
    spec = learner_spec(first.settings, first.run_state)
    holder = ProcessActors(LearnerService, [{"spec": spec}])  # the first run's learner
    second = RealRL.start(_settings(demos, tmp_path / "b", learner_folder=folder))
    try:
        with pytest.raises(LearnError, match=r"the learner folder .* is locked by process \d+"):
            second.run()
        assert second.run_state.agent.env_steps == 0  # the robot never moved
    finally:
        second.close()
        holder.close()
        first.close()
    # Once the first learner has stopped, its folder is taken up again, from its checkpoint.
    again = LearnerService(spec)
    assert again.status().updates == spec.rl.offline_steps
    again.close()


def test_a_learner_that_does_not_answer_in_time_is_stopped_and_the_robot_goes_on(demos, tmp_path):
    """A learner that takes longer than ``learner_timeout`` to answer an episode is
    stopped and taken for lost: the robot acts on with the weights it has, and every
    episode stays in the actor's session for the learner that starts next."""
    said = []
    real = RealRL.start(
        _settings(demos, tmp_path / "run", plant_steps=101, learner_timeout=0.01),
        on_notice=said.append,
    )
    run = real.run()
    episodes = Session(tmp_path / "run" / "session").episode_paths()
    assert len(episodes) == len(run.history) >= 2 and run.agent.env_steps >= 101
    assert any("did not answer episode within 0.01 s" in m for m in said)
    # A learner started again has the same time: none starts within 0.01 s, the robot goes on.
    assert any(
        "a learner could not start again" in m and "did not answer its start within 0.01 s" in m
        for m in said
    )
    assert run.agent.updates == RLConfig.for_method("twinrl", offline_steps=3).offline_steps
    # The stopped learner freed its folder: one starts there again, from its checkpoint.
    from twinrl_learn.real_rl import learner_spec
    from twinrl_learn.remote_learner import LearnerService

    again = LearnerService(learner_spec(real.settings, run))
    again.close()
    with pytest.raises(SettingError, match="learner_timeout"):
        _settings(demos, tmp_path, learner_timeout=0)


def test_an_actor_whose_learner_lags_says_so_and_acts_on(demos, tmp_path, monkeypatch):
    """Without ``learner_sync`` the learner answers an episode at once and runs the
    updates it bought meanwhile; an actor whose learner owes more than
    ``BEHIND_STEPS`` robot steps of them says so and acts with the weights it has."""
    import twinrl_learn.remote_learner as remote

    monkeypatch.setattr(remote, "BEHIND_STEPS", 0)  # any debt at all is "behind"
    said = []
    settings = _settings(demos, tmp_path / "run", plant_steps=101, learner_sync=False)
    run = RealRL.start(settings, on_notice=said.append).run()
    assert len(Session(tmp_path / "run" / "session").episode_paths()) == len(run.history) >= 2
    behind = [m for m in said if "updates behind the robot" in m]
    assert behind and all(float(m.split()[3]) > 0 for m in behind)
