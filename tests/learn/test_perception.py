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


def test_a_narrower_head_trains_and_loads_and_old_checkpoints_keep_theirs(trained, tmp_path):
    _, dataset, out, _ = trained
    narrow = tmp_path / "narrow"
    train_estimator(
        PerceptionSettings(datasets=[str(dataset)], out=str(narrow), steps=2, batch_size=8,
                           head_width=16)
    )  # fmt: skip
    loaded = PoseEstimator.from_pretrained(narrow)
    assert loaded.config.head_width == 16 and loaded.heads["front"].mix[1].out_channels == 16
    default = PoseEstimator.from_pretrained(out)
    assert sum(p.numel() for p in loaded.parameters()) < sum(
        p.numel() for p in default.parameters()
    )
    # A checkpoint written before the width was a setting has none: it had 64 channels.
    old = tmp_path / "old"
    old.mkdir()
    config = json.loads((out / "config.json").read_text())
    del config["head_width"]
    (old / "config.json").write_text(json.dumps(config))
    (old / "model.safetensors").write_bytes((out / "model.safetensors").read_bytes())
    assert PoseEstimator.from_pretrained(old).heads["front"].mix[1].out_channels == 64
    with pytest.raises(SettingError, match="head_width"):
        PerceptionSettings(datasets=[str(dataset)], out=str(tmp_path / "e"), head_width=20)


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


def test_objects_are_placed_in_the_world_where_the_estimates_say(trained):
    """world_poses inverts the estimator's targets (the relative poses a perfect
    estimator would say) back into the logged world poses."""
    from twinrl_learn.policy.inputs import relative_poses
    from twinrl_learn.seeing_operator import world_poses
    from twinrl_sim.tasks import make_task

    folder, _, out, _ = trained
    episode = read_episode(Session(folder / "session").episode_paths()[0])
    names = make_task("pick_place").scene.object_names
    order = PoseEstimator.from_pretrained(out).config.objects
    state = episode.data["observation.state"]
    environment = episode.data["observation.environment_state"]
    tcp = episode.meta.names["observation.state"].index("tcp.x")
    exact = relative_poses(
        torch.as_tensor(state), torch.as_tensor(environment), tcp,
        [7 * names.index(n) for n in order], True,
    ).numpy()  # fmt: skip
    for row in range(0, len(state), 7):
        poses = world_poses(exact[row], state[row], tcp)
        for k, name in enumerate(order):
            truth = environment[row, 7 * names.index(name) : 7 * names.index(name) + 7]
            np.testing.assert_allclose(poses[k, :3], truth[:3], atol=1e-5)
            assert abs(abs(np.dot(poses[k, 3:], truth[3:])) - 1) < 1e-5  # q and -q alike


def test_the_seeing_operator_judges_progress_on_what_it_sees(trained, tmp_path):
    """Given exact estimates, the operator's twin says success exactly where the episode
    did (the settled frames after it); with the trained estimator it sees the objects
    within its error, and it never asks for the plant's progress."""
    from twinrl_learn.policy.inputs import relative_poses
    from twinrl_learn.seeing_operator import SeeingOperator, world_poses
    from twinrl_robot.scripted import run_scripted_expert
    from twinrl_sim.tasks import TaskConfig, make_task

    _, _, out, _ = trained
    session = Session.create(tmp_path / "session")
    run_scripted_expert("pick_place", world="twin", episodes=1, regions=("ID",), seed=8,
                        session=session, settle=3)  # fmt: skip
    episode = read_episode(session.episode_paths()[0])
    assert episode.meta.success
    task = make_task("pick_place")
    estimator = PoseEstimator.from_pretrained(out)
    operator = SeeingOperator(estimator, seed=0)
    assert operator.judges_progress is False and operator.cameras == ("front", "wrist")
    state = episode.data["observation.state"]
    environment = episode.data["observation.environment_state"]
    tcp = episode.meta.names["observation.state"].index("tcp.x")
    names = task.scene.object_names
    indices = [7 * names.index(n) for n in estimator.config.objects]
    exact = relative_poses(torch.as_tensor(state), torch.as_tensor(environment), tcp, indices,
                           True)  # fmt: skip

    class Perfect:
        """A perfect estimator: the logged poses, as an estimator says them."""

        config = estimator.config
        row = 0

        def estimate(self, images, state):
            return exact[self.row][None]

    def observation(t):
        return {
            "observation.state": state[t],
            "observation.environment_state": np.zeros_like(environment[t]),  # never read
            **{f"observation.images.{c}": episode.images[c][t] for c in ("front", "wrist")},
        }

    perfect = Perfect()
    operator.estimator = perfect
    operator.reset(task, TaskConfig.from_dict(episode.meta.config))
    judged = []
    for t in range(len(state)):
        perfect.row = t
        seen, progress = operator.seen(observation(t))
        np.testing.assert_allclose(seen["observation.environment_state"], environment[t], atol=1e-4)
        judged.append(progress.success)
    succeeded = np.asarray(episode.data["next.success"], bool)
    first = int(np.argmax(succeeded))
    assert judged[: first + 1] == [False] * (first + 1) and all(judged[first + 1 :])
    # The trained estimator (a tiny one): what the operator sees is what it says.
    operator.estimator = estimator
    operator.reset(task, TaskConfig.from_dict(episode.meta.config))
    seen, _ = operator.seen(observation(0))
    images = {c: episode.images[c][:1] for c in ("front", "wrist")}
    said = world_poses(estimator.estimate(images, state[:1])[0].numpy(), state[0], tcp)
    order = [estimator.config.objects.index(n) for n in names]
    np.testing.assert_allclose(seen["observation.environment_state"], said[order].ravel(),
                               atol=1e-5)  # fmt: skip
    assert operator.intervene(observation(1), None) is None  # it watches before acting
    with pytest.raises(LearnError, match="watches camera front"):
        operator.intervene({"observation.state": state[2]}, None)


def test_real_rl_with_an_operator_who_sees_reads_no_progress_from_the_plant(trained, tmp_path):
    """`operator_sees`: the simulated operator is the one that sees through the estimator,
    the cell records the cameras it watches (the state policy needs none), and the plant's
    progress never reaches it."""
    from tests.conftest import tiny_state_policy
    from twinrl_learn.real_rl import RealRL
    from twinrl_learn.seeing_operator import SeeingOperator
    from twinrl_learn.settings import RealRLSettings, RLConfig
    from twinrl_robot.operator import OperatorRule

    _, _, out, _ = trained
    dataset, sft = tiny_state_policy(tmp_path / "sft", seed=5, steps=20)
    heard = []
    original = SeeingOperator.intervene
    SeeingOperator.intervene = lambda self, obs, progress: (
        heard.append(progress) or original(self, obs, progress)
    )
    try:
        real = RealRL.start(
            RealRLSettings(
                task="pick_place", init=str(sft), out=str(tmp_path / "run"), demos=[str(dataset)],
                plant_steps=30, eval_every=0, eval_grid=(1, 1), refresh_every=0,
                show_resets=False, operator=OperatorRule(patience=3, delay=1),
                operator_sees=str(out),
                rl=RLConfig.for_method("twinrl", offline_steps=2, batch_size=16, seed=1),
            )
        )  # fmt: skip
        assert isinstance(real.operator, SeeingOperator)
        run = real.run()
    finally:
        SeeingOperator.intervene = original
    assert run.agent.env_steps >= 30 and heard and all(p is None for p in heard)
    episode = read_episode(Session(tmp_path / "run" / "session").episode_paths()[0])
    assert set(episode.images) == {"front", "wrist"}  # what the operator watched
    with pytest.raises(SettingError, match="operator_sees"):
        RealRLSettings(task="pick_place", init=str(sft), out=str(tmp_path / "x"),
                       operator=None, operator_sees=str(out))  # fmt: skip
