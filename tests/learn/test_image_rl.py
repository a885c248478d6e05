"""The image policy through Stages II and III: what the paper preset runs, at toy scale."""

import json

import numpy as np
import pytest
import torch

from tests.conftest import record_demos
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.agent import Agent
from twinrl_learn.mining import mine
from twinrl_learn.perception import train_estimator
from twinrl_learn.policy import Policy
from twinrl_learn.real_rl import RealRL, RealRLSettings
from twinrl_learn.real_rl_progress import load_evaluations
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.settings import PerceptionSettings, RLConfig, SFTConfig
from twinrl_learn.sft import train_sft
from twinrl_learn.twin_rl import TwinRLSettings, run_twin_rl
from twinrl_robot.operator import OperatorRule


@pytest.fixture(scope="module")
def image_demos(tmp_path_factory):
    """An expert demo with both cameras and an image policy briefly trained on it."""
    folder = tmp_path_factory.mktemp("image_rl")
    dataset = record_demos(folder / "demos", seed=5)
    sft = folder / "sft"
    train_sft(
        SFTConfig(
            datasets=[str(dataset)], out=str(sft), policy="vla", steps=2, batch_size=4,
            chunk=4, image_size=64,
        )
    )  # fmt: skip
    return dataset, sft


@pytest.mark.parametrize(
    ("method", "offline", "passes"),
    # observations and next observations, plus the demo rows' shifted images to imitate
    [("hil-serl", 0, 2), ("twinrl", 1, 3), ("twinrl", 0, 3)],
)
def test_an_update_encodes_each_image_batch_once(image_demos, method, offline, passes):
    dataset, sft = image_demos
    policy = Policy.from_pretrained(sft)
    agent = Agent(policy, RLConfig.for_method(method, offline_steps=offline, batch_size=8))
    assert agent.online() == (offline == 0)
    buffer = ReplayBuffer.from_datasets([dataset], cameras=policy.config.cameras)
    batch = buffer.sample(8, np.random.default_rng(0), chunk=4, gamma=0.98)
    calls = {camera: 0 for camera in policy.config.cameras}
    for camera, encoder in policy.encoders.items():
        encoder.register_forward_hook(lambda *_, c=camera: calls.__setitem__(c, calls[c] + 1))
    agent.update(batch)
    assert calls == {camera: passes for camera in policy.config.cameras}


@pytest.mark.slow
@pytest.mark.parametrize(
    "perceiving",
    [False, pytest.param(True, marks=pytest.mark.long)],  # the estimator's beyond CI's time
    ids=["own encoders", "estimator"],
)
def test_the_image_policy_runs_through_twin_rl_mining_and_real_rl(
    image_demos, tmp_path, perceiving
):
    torch.set_num_threads(1)
    dataset, sft = image_demos
    if perceiving:  # acting through a pose estimator trained on the same twin episodes
        train_estimator(PerceptionSettings(datasets=[str(dataset)], out=str(tmp_path / "est"),
                                           steps=5, batch_size=8))  # fmt: skip
        sft = tmp_path / "sft"
        train_sft(
            SFTConfig(datasets=[str(dataset)], out=str(sft), policy="vla", steps=2,
                      batch_size=4, chunk=4, perception=str(tmp_path / "est"))
        )  # fmt: skip
    policy = Policy.from_pretrained(sft)
    assert policy.perceives if perceiving else policy.locates
    rl = RLConfig(offline_steps=2, batch_size=8, utd=0.02, seed=1)

    twin = run_twin_rl(
        TwinRLSettings(
            task="pick_place", init=str(sft), out=str(tmp_path / "twin"), demos=[str(dataset)],
            envs=1, steps=1, rl=rl, failures=1,
        )
    )  # fmt: skip
    assert twin.agent.updates > rl.offline_steps
    (episode_path,) = Session(tmp_path / "twin" / "session").episode_paths()
    rollout = read_episode(episode_path)
    assert rollout.meta.source == "twin_rl"
    assert rollout.images["front"].shape == (len(rollout), 128, 128, 3)
    buffer = tmp_path / "twin" / "twin_buffer"
    assert json.loads((buffer / "meta" / "info.json").read_text())["total_episodes"] == 1

    targets = tmp_path / "targets.json"
    mine(TwinrlRunner(tmp_path / "twin" / "agent"), "pick_place", out=targets, grid=(1, 2),
         episodes=1, k=2, tau=1.0)  # fmt: skip
    assert json.loads(targets.read_text())["targets"]

    real = RealRL.start(
        RealRLSettings(
            task="pick_place", init=str(tmp_path / "twin" / "agent"), out=str(tmp_path / "real"),
            demos=[str(dataset)], twin_buffer=str(buffer), targets=str(targets),
            plant_steps=20, eval_every=0, eval_grid=(1, 2), refresh_every=0,
            operator=OperatorRule(patience=3, delay=1), rl=rl,
        )
    )  # fmt: skip
    run = real.run()
    assert run.agent.env_steps >= 20
    episodes = [read_episode(p) for p in Session(tmp_path / "real" / "session").episode_paths()]
    assert {e.meta.source for e in episodes} == {"real_rl"}
    assert all(e.images["wrist"].shape[0] == len(e) for e in episodes)
    # The buffers hold the cameras' frames, of every real-RL episode too (one the
    # operator helped in as a demonstration).
    assert run.online.cameras == run.demo.cameras == ("front", "wrist")
    # A perceiving policy's buffers hold its estimates too, computed once per episode.
    assert (run.online.estimate is not None) == (run.demo.estimate is not None) == perceiving
    buffered = {e.meta.episode_id for e in run.online.episodes + run.demo.episodes}
    assert {e.meta.episode_id for e in episodes} <= buffered
    assert [p.plant_steps for p in load_evaluations(tmp_path / "real")] == [0, run.agent.env_steps]
