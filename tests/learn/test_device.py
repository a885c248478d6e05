"""Where the networks run (`--device`): bad names and a GPU asked for where there is none
are refused in one line before anything is written; on a machine with a CUDA GPU, what
trains there (estimator, SFT, an RL agent, a reward classifier) loads and acts on the CPU
as it does on the GPU."""

import numpy as np
import pytest
import torch

from tests.conftest import record_demos
from tests.test_cli import twinrl
from twinrl_data.errors import SettingError
from twinrl_learn.compute import check_device, resolve_device
from twinrl_learn.settings import PerceptionSettings, SFTConfig, TwinRLSettings

GPU = torch.cuda.is_available()


def test_device_names_are_refused_before_any_work(tmp_path):
    for good in ("auto", "cpu", "cuda", "cuda:1"):
        check_device(good)
    for bad in ("gpu", "CUDA", "cuda:", "tpu", ""):
        with pytest.raises(SettingError, match="device"):
            check_device(bad)
    with pytest.raises(SettingError, match="auto, cpu, cuda"):
        SFTConfig(datasets=["d"], out=str(tmp_path / "o"), device="gpu")
    with pytest.raises(SettingError, match="device"):
        PerceptionSettings(datasets=["d"], out=str(tmp_path / "o"), device="gpu")
    with pytest.raises(SettingError, match="device"):
        TwinRLSettings(task="pick_place", init="x", out=str(tmp_path / "o"), device="mps")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if GPU else "cpu")
    for command in (
        ("train", "sft", "--dataset", str(tmp_path), "--out", str(tmp_path / "o")),
        ("eval", "expert", "--task", "pick_place", "--out", str(tmp_path / "o")),
        ("demo", "--preset", "smoke", "--out", str(tmp_path / "o")),
    ):
        result = twinrl(*command, "--device", "gpu")
        assert result.returncode != 0 and "--device" in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(GPU, reason="needs a machine without a CUDA GPU")
def test_a_gpu_asked_for_where_there_is_none_is_refused(tmp_path):
    with pytest.raises(SettingError, match="no CUDA GPU"):
        resolve_device("cuda")
    result = twinrl(
        "train", "sft", "--dataset", str(tmp_path), "--out", str(tmp_path / "o"),
        "--device", "cuda",
    )  # fmt: skip
    assert result.returncode != 0 and "no CUDA GPU" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(not GPU, reason="needs a CUDA GPU")
def test_what_trains_on_a_gpu_loads_and_acts_on_the_cpu(tmp_path):
    from twinrl_data.mcap_log import read_episode
    from twinrl_data.session import Session
    from twinrl_learn.agent import Agent
    from twinrl_learn.perception import PoseEstimator, train_estimator
    from twinrl_learn.policy import Policy
    from twinrl_learn.replay import ReplayBuffer
    from twinrl_learn.reward_classifier import (
        ClassifierSettings,
        RewardClassifier,
        train_reward_classifier,
    )
    from twinrl_learn.settings import RLConfig
    from twinrl_learn.sft import train_sft

    dataset = record_demos(tmp_path, episodes=2, seed=5)  # two per region
    estimator = tmp_path / "estimator"
    train_estimator(
        PerceptionSettings(datasets=[str(dataset)], out=str(estimator), steps=30,
                           batch_size=32, log_every=10, device="cuda")
    )  # fmt: skip
    episode = read_episode(Session(tmp_path / "session").episode_paths()[0])
    images = {c: episode.images[c][:4] for c in ("front", "wrist")}
    state = episode.data["observation.state"][:4]
    on_gpu = PoseEstimator.from_pretrained(estimator, "cuda").estimate(images, state)
    on_cpu = PoseEstimator.from_pretrained(estimator).estimate(images, state)
    assert on_gpu.device.type == "cpu"  # estimates come back to the CPU
    assert torch.allclose(on_gpu, on_cpu, atol=0.05)  # bfloat16 on the GPU

    for kind, perception in (("state", None), ("vla", str(estimator)), ("vla", None)):
        out = tmp_path / f"sft_{kind}_{perception is not None}"
        train_sft(SFTConfig(datasets=[str(dataset)], out=str(out), policy=kind, steps=20,
                            batch_size=16, perception=perception, device="cuda"))  # fmt: skip
        gpu_policy = Policy.from_pretrained(out, "cuda")
        cpu_policy = Policy.from_pretrained(out)
        assert gpu_policy.device.type == "cuda" and cpu_policy.device.type == "cpu"
        observation = {
            "observation.state": episode.data["observation.state"][:2],
            "observation.environment_state": episode.data["observation.environment_state"][:2],
            **{f"observation.images.{c}": episode.images[c][:2] for c in ("front", "wrist")},
        }
        instruction = [episode.meta.instruction] * 2
        expected = cpu_policy.act_chunks(observation, instruction)
        actual = gpu_policy.act_chunks(observation, instruction)
        assert actual.dtype == np.float32 and np.allclose(actual, expected, atol=0.02)

        # An RL agent updates on the GPU and its checkpoint resumes on the CPU.
        buffer = ReplayBuffer.from_datasets([str(dataset)], **gpu_policy.replay_views())
        config = RLConfig.for_method("twinrl", seed=0, offline_steps=1, batch_size=16)
        agent = Agent(gpu_policy, config)
        rng = np.random.default_rng(0)
        for _ in range(3):  # one offline (Cal-QL) update, then online ones
            batch = buffer.sample(16, rng, chunk=gpu_policy.config.chunk, gamma=config.gamma)
            metrics = agent.update(batch)
            assert all(np.isfinite(v) for v in metrics.values())
        agent.save(tmp_path / f"agent_{kind}")
        again = Agent.load(tmp_path / f"agent_{kind}")
        assert again.device.type == "cpu" and again.updates == 3
        again.update(batch)

    classifier = tmp_path / "classifier"
    episodes = [read_episode(p) for p in Session(tmp_path / "session").episode_paths()]
    train_reward_classifier(
        episodes, classifier, ClassifierSettings(steps=20, heldout=0.25), device="cuda"
    )
    last = {
        "observation.state": episode.data["observation.state"][-1],
        "observation.images.front": episode.images["front"][-1],
    }
    assert 0.0 <= RewardClassifier.load(classifier).probability(last) <= 1.0
