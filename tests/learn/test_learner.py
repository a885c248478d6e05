"""The learner apart from the robot loop: the loop never waits for an update, a seed
still gives the same run, and a learner's failure reaches the actor."""

import threading

import numpy as np
import pytest

from tests.conftest import tiny_state_policy
from tests.learn.test_real_rl import real_settings
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.agent import Agent
from twinrl_learn.learner import Learner
from twinrl_learn.online import OnlineRun
from twinrl_learn.policy import Policy
from twinrl_learn.real_rl import RealRL
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.settings import RLConfig


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return tiny_state_policy(tmp_path_factory.mktemp("learner"), seed=6, steps=20)


def small_run(demos, out, utd=2):
    dataset, sft = demos
    policy = Policy.from_pretrained(sft)
    config = RLConfig.for_method("twinrl", offline_steps=0, batch_size=8, utd=utd, seed=0)
    demo = ReplayBuffer.from_datasets([str(dataset)], rewards=config.rewards)
    return OnlineRun.start(out, Agent(policy, config), demo)


def test_the_learner_runs_utd_updates_per_granted_step(demos, tmp_path):
    run = small_run(demos, tmp_path / "run", utd=2)
    learner = Learner(run)
    try:
        for _ in range(3):
            learner.grant(1)
        assert learner.wait(timeout_s=60)
        assert run.agent.updates == 6 and run.agent.env_steps == 3
        assert learner.metrics and all(np.isfinite(v) for v in learner.metrics.values())
        before = learner.weights()
        learner.grant(1)
        learner.wait(timeout_s=60)
        after = learner.weights()
        assert any(not np.array_equal(before[k], after[k]) for k in before)
    finally:
        learner.close()


def test_acting_never_waits_for_an_update(demos, tmp_path):
    """An update hangs until released: meanwhile the robot steps on, granting more."""
    run = small_run(demos, tmp_path / "run", utd=1)
    entered, release = threading.Event(), threading.Event()
    update = run.update

    def hanging_update():
        entered.set()
        release.wait()
        return update()

    run.update = hanging_update
    learner = Learner(run)
    try:
        learner.grant(1)
        assert entered.wait(timeout=60)  # the learner is inside its first update
        actor = threading.Thread(target=lambda: [learner.grant(1) for _ in range(49)])
        actor.start()
        actor.join(timeout=10)
        assert not actor.is_alive(), "granting steps waited for the update in progress"
        assert run.agent.updates == 0 and run.agent.env_steps == 50
        assert not learner.wait(timeout_s=0.05)
        release.set()
        assert learner.wait(timeout_s=120) and run.agent.updates == 50
    finally:
        release.set()
        learner.close()


def test_a_failing_update_reaches_the_actor(demos, tmp_path):
    run = small_run(demos, tmp_path / "run")

    def broken_update():
        raise FloatingPointError("NaN in the critic loss")

    run.update = broken_update
    learner = Learner(run)
    learner.grant(1)
    with pytest.raises(RuntimeError, match="learner thread stopped") as caught:
        learner.wait(timeout_s=60)
    assert isinstance(caught.value.__cause__, FloatingPointError)
    learner.close()


def test_with_the_learner_in_its_thread_a_seed_gives_the_same_run(demos, tmp_path):
    sessions = []
    for name in ("a", "b"):
        real = RealRL.start(real_settings(demos, tmp_path / name, plant_steps=40))
        run = real.run()
        assert run.agent.updates == run.agent.config.offline_steps + run.agent.env_steps
        sessions.append(
            [read_episode(p) for p in Session(tmp_path / name / "session").episode_paths()]
        )
    assert len(sessions[0]) == len(sessions[1])
    for first, second in zip(*sessions, strict=True):
        np.testing.assert_array_equal(
            first.data["observation.state"], second.data["observation.state"]
        )
    timing = (tmp_path / "a" / "timing.json").read_text()
    assert '"p99_s"' in timing
