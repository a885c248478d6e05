"""Perception from the twin: the pretrained backbone, the pose estimator's training and
checkpoint, an image policy that acts through it, and `twinrl locate` on it."""

import json

import numpy as np
import pytest
import torch

from tests.conftest import record_demos
from tests.test_cli import twinrl
from twinrl_data.errors import SettingError
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.errors import LearnError
from twinrl_learn.locating import Locator, episode_errors
from twinrl_learn.perception import PerceptionSettings, PoseEstimator, train_estimator
from twinrl_learn.perception.backbone import FrozenBackbone
from twinrl_learn.perception.training import gather_frames, targets
from twinrl_learn.policy import Policy
from twinrl_learn.settings import SFTConfig
from twinrl_learn.sft import train_sft


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A twin demo per region with both cameras and object poses, and an estimator trained on
    them for a few hundred steps."""
    folder = tmp_path_factory.mktemp("perception")
    dataset = record_demos(folder, seed=5)  # one per region
    out = folder / "estimator"
    result = train_estimator(
        PerceptionSettings(datasets=[str(dataset)], out=str(out), steps=150, batch_size=32,
                           log_every=50)
    )  # fmt: skip
    return folder, dataset, out, result


def test_the_shipped_imagenet_weights_are_mapped_onto_the_architecture():
    """A photo of a cat is a cat (ImageNet classes 281-285): the registry package's
    weights sit in the right tensors of timm's EfficientNet-Lite0."""
    import skimage.data
    import timm

    from twinrl_learn.perception.backbone import ARCHITECTURE, _pretrained_state_dict

    model = timm.create_model(ARCHITECTURE, pretrained=False)
    model.load_state_dict(_pretrained_state_dict(model))
    model.eval()
    x = torch.from_numpy(skimage.data.chelsea()).permute(2, 0, 1)[None].float() / 255
    x = torch.nn.functional.interpolate(x, size=(224, 224), mode="bilinear", antialias=True)
    backbone = FrozenBackbone()
    with torch.no_grad():
        top = model((x - backbone.mean) / backbone.std).argmax().item()
    assert 281 <= top <= 285
    fine, coarse = backbone(torch.rand(2, 3, 128, 128))
    assert fine.shape == (2, 40, 16, 16) and coarse.shape == (2, 112, 8, 8)
    assert not any(p.requires_grad for p in backbone.encoder.parameters())


def test_the_estimator_learns_and_its_checkpoint_says_the_same(trained):
    _, dataset, out, result = trained
    assert (out / "loss.png").is_file()
    record = json.loads((out / "training.json").read_text())
    assert record["episodes"] == 2 and record["held_out_episodes"] == 1
    assert set(result.held_out_errors) == {"banana", "plate"}
    # It learnt something: the training loss fell by far.
    assert np.mean(result.losses[-20:]) < np.mean(result.losses[:20]) / 3
    estimator = PoseEstimator.from_pretrained(out)
    frames = gather_frames([dataset])
    rows = slice(0, 8)
    images = {c: frames.images[c][rows] for c in estimator.config.cameras}
    again = PoseEstimator.from_pretrained(out).estimate(images, frames.state[rows])
    first = estimator.estimate(images, frames.state[rows])
    assert torch.equal(first, again)
    assert first.shape == (8, 18) == targets(frames)[rows].shape


def test_bad_perception_input_is_refused_in_one_line(trained, tmp_path):
    _, dataset, out, _ = trained
    with pytest.raises(LearnError, match="not empty"):
        train_estimator(PerceptionSettings(datasets=[str(dataset)], out=str(out), steps=1))
    with pytest.raises(SettingError, match="steps"):
        PerceptionSettings(datasets=[str(dataset)], out=str(tmp_path / "e"), steps=0)
    with pytest.raises(LearnError, match="is not a pose estimator"):
        PoseEstimator.from_pretrained(tmp_path)
    with pytest.raises(SettingError, match="perception"):
        SFTConfig(datasets=[str(dataset)], out=str(tmp_path / "s"), policy="state",
                  perception=str(out))  # fmt: skip
    before = (out / "model.safetensors").read_bytes()
    result = twinrl("train", "perception", "--dataset", str(dataset), "--out", str(out))
    assert result.returncode != 0 and "not empty" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert (out / "model.safetensors").read_bytes() == before


def test_an_image_policy_acts_through_the_estimator(trained, tmp_path):
    folder, dataset, out, _ = trained
    checkpoint = tmp_path / "vla"
    train_sft(
        SFTConfig(datasets=[str(dataset)], out=str(checkpoint), policy="vla",
                  perception=str(out), steps=3, batch_size=8)
    )  # fmt: skip
    policy = Policy.from_pretrained(checkpoint)
    estimator = PoseEstimator.from_pretrained(out)
    assert policy.perceives and not policy.locates and policy.needs_images
    # The checkpoint carries the estimator it was trained with: no other file needed.
    for name, value in estimator.state_dict().items():
        assert torch.equal(policy.state_dict()[f"estimator.{name}"], value)
    episode = read_episode(Session(folder / "session").episode_paths()[0])
    observation = {
        "observation.state": episode.data["observation.state"][:1],
        **{f"observation.images.{c}": episode.images[c][:1] for c in ("front", "wrist")},
    }
    batch = policy.observation_inputs(observation, [episode.meta.instruction])
    expected = estimator.estimate(
        {c: episode.images[c][:1] for c in ("front", "wrist")},
        episode.data["observation.state"][:1],
    )
    assert torch.allclose(batch["relative"], expected)
    assert "observation.environment_state" not in observation  # nothing privileged read
    action = policy.act({k: v[0] for k, v in observation.items()}, episode.meta.instruction)
    assert action.shape == (7,) and np.isfinite(action).all()
    # Where it sees the objects is its estimator's view.
    error, distance = episode_errors(policy, episode)
    alone, _ = episode_errors(Locator(estimator), episode)
    assert np.allclose(error, alone, atol=1e-5) and error.shape == distance.shape


def test_locate_reports_an_estimator_folder(trained, tmp_path):
    _, dataset, out, _ = trained
    result = twinrl("locate", str(out), f"demos={dataset}", "--out", str(tmp_path / "loc"))
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "loc" / "locating.json").read_text())
    assert set(report["sources"]["demos"]["ID"]) == {"banana", "plate"}
    assert "median planar locating error" in result.stdout


def test_rl_updates_of_a_perceiving_policy_read_estimates_computed_once(trained, tmp_path):
    from twinrl_learn.agent import Agent
    from twinrl_learn.perception.backbone import FrozenBackbone
    from twinrl_learn.replay import ReplayBuffer
    from twinrl_learn.settings import RLConfig

    _, dataset, out, _ = trained
    checkpoint = tmp_path / "vla"
    train_sft(
        SFTConfig(datasets=[str(dataset)], out=str(checkpoint), policy="vla",
                  perception=str(out), steps=2, batch_size=8, chunk=4)
    )  # fmt: skip
    policy = Policy.from_pretrained(checkpoint)
    views = policy.replay_views()
    assert views["cameras"] == ("front", "wrist") and views["estimate"] is not None
    passes = []
    original = FrozenBackbone.__call__
    FrozenBackbone.__call__ = lambda self, x: passes.append(len(x)) or original(self, x)
    try:
        buffer = ReplayBuffer.from_datasets([dataset], **views)
        rng = np.random.default_rng(0)
        batch = buffer.sample(8, rng, chunk=4, gamma=0.98)
        once = sum(passes)
        assert once == 2 * len(buffer)  # every step's two cameras, once
        agent = Agent(policy, RLConfig.for_method("twinrl", offline_steps=0, batch_size=8))
        agent.update(batch)
        agent.update(buffer.sample(8, rng, chunk=4, gamma=0.98))
        assert sum(passes) == once  # updates ran no image network
    finally:
        FrozenBackbone.__call__ = original
    assert batch.estimates.shape == batch.next_estimates.shape == (8, 18)
