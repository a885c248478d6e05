"""Policy, SFT, evaluation and the lerobot adapter on a small recorded dataset."""

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import record_demos, stage1_smoke
from twinrl_data.errors import SettingError
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_data.training import load_frames
from twinrl_learn.evaluate import evaluate, grid_cells
from twinrl_learn.policy import (
    IMAGE_SHIFT,
    STATE_NOISE,
    FiLMConvEncoder,
    Policy,
    PolicyConfig,
)
from twinrl_learn.runners import ExpertRunner, TwinrlRunner, load_runner
from twinrl_learn.settings import SFTConfig
from twinrl_learn.sft import learning_rate, train_sft
from twinrl_robot.wrappers import HoldRule
from twinrl_sim.build import yaw_quat
from twinrl_sim.tasks.expert import tool_quat


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return record_demos(tmp_path_factory.mktemp("demos"), episodes=2, seed=1)


@pytest.fixture(scope="module")
def state_checkpoint(dataset, tmp_path_factory):
    """A few SFT steps of the state policy: something a runner can load and act with."""
    out = tmp_path_factory.mktemp("state") / "p"
    train_sft(
        SFTConfig(datasets=[str(dataset)], out=str(out), policy="state", steps=5, batch_size=8)
    )
    return out


@pytest.mark.parametrize(
    ("kind", "inputs"), [("state", "absolute"), ("state", "relative"), ("vla", "absolute")]
)
def test_sft_loss_decreases_and_checkpoints_round_trip(dataset, tmp_path, kind, inputs):
    result = train_sft(
        SFTConfig(
            datasets=[str(dataset)],
            out=str(tmp_path / kind),
            policy=kind,
            inputs=inputs,
            steps=60,
            batch_size=16,
            checkpoint_every=30,
            log_every=10,
        )
    )
    assert np.mean(result.losses[-10:]) < np.mean(result.losses[:10])
    assert (tmp_path / kind / "loss.png").stat().st_size > 1000
    assert (tmp_path / kind / "checkpoints" / "step_000030" / "model.safetensors").is_file()
    policy = Policy.from_pretrained(tmp_path / kind)
    again = Policy.from_pretrained(tmp_path / kind)
    episode = read_episode(
        next(iter(sorted((dataset.parent / "session" / "episodes").glob("*.mcap"))))
    )
    observation = {
        "observation.state": episode.data["observation.state"][0],
        "observation.environment_state": episode.data["observation.environment_state"][0],
        **{f"observation.images.{c}": f[0] for c, f in episode.images.items()},
    }
    np.testing.assert_array_equal(
        policy.act(observation, "put the banana on the plate"),
        again.act(observation, "put the banana on the plate"),
    )
    assert policy.act(observation, "put the banana on the plate").shape == (7,)
    assert policy.config.inputs == inputs
    names = episode.meta.names["observation.state"]
    read = {names[i].split(".")[0] for i in policy.config.state_inputs}
    assert read == ({"tcp", "gripper"} if inputs == "relative" else {"q", "tcp", "gripper"})


def test_relative_inputs_are_the_same_reach_anywhere_on_the_table():
    config = PolicyConfig(
        kind="state", state_dim=8, env_dim=7, tcp_index=0, object_indices=[0], inputs="relative"
    )
    policy = Policy(config)

    def poses(shift, tool_yaw, object_yaw):
        state = torch.tensor([[0.4 + shift[0], shift[1], 0.2, *tool_quat(tool_yaw), 0.08]])
        env = torch.tensor([[0.5 + shift[0], 0.1 + shift[1], 0.02, *yaw_quat(object_yaw)]])
        return policy.relative_poses(state.float(), env.float())

    here = poses((0.0, 0.0), 0.3, 0.9)
    assert here.shape == (1, 9) == (1, policy.relative_width)
    torch.testing.assert_close(poses((-0.2, 0.35), 0.3, 0.9), here)  # moved across the table
    torch.testing.assert_close(poses((0.0, 0.0), 0.5, 1.1)[:, 3:], here[:, 3:])  # both turned
    assert not torch.allclose(poses((0.0, 0.0), 0.3, 1.4)[:, 3:], here[:, 3:])
    with pytest.raises(ValueError, match="relative inputs need the state policy"):
        PolicyConfig(kind="vla", state_dim=8, inputs="relative")
    with pytest.raises(ValueError, match="inputs applies to the state policy only"):
        train_sft(SFTConfig(datasets=["nowhere"], out="x", policy="vla", inputs="relative"))


def test_acting_averages_every_prediction_for_a_step_or_runs_chunks_open_loop():
    """Temporal ensembling: the action for step t is the exp(-m * i)-weighted mean of the
    predictions made at steps t-3..t for it (i = 0 the oldest); open-loop: one prediction
    per chunk, its actions in turn."""
    config = PolicyConfig(
        kind="state", state_dim=8, env_dim=7, chunk=4, temporal_ensemble=0.5, grasp_hold=False
    )
    policy = Policy(config)
    made = []

    def predict(batch, instructions, deterministic=True, std_scale=1.0):
        step = len(made)
        made.append(step)  # step s predicts s*10 + k for the k-th step ahead
        return np.array([[[step * 10.0 + k] * 7 for k in range(4)]], np.float32)

    policy.act_chunks = predict
    observation = {"observation.state": np.zeros(8), "observation.environment_state": np.zeros(7)}
    actions = [policy.act(observation, "")[0] for _ in range(6)]
    weights = np.exp(-0.5 * np.arange(4))
    # step 5 was predicted by steps 2..5 as 2*10+3, 3*10+2, 4*10+1 and 5*10+0
    assert actions[5] == pytest.approx(weights @ [23.0, 32.0, 41.0, 50.0] / weights.sum())
    assert actions[0] == 0.0 and actions[1] == pytest.approx(
        (1 + np.exp(-0.5) * 10) / (1 + np.exp(-0.5))
    )
    policy.reset()
    made.clear()
    policy.config.temporal_ensemble = None
    actions = [policy.act(observation, "")[0] for _ in range(6)]
    assert actions == [0.0, 1.0, 2.0, 3.0, 10.0, 11.0] and made == [0, 1]
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="temporal_ensemble must be a finite number >= 0"):
            PolicyConfig(kind="state", state_dim=8, env_dim=7, temporal_ensemble=bad)


def test_the_arm_holds_while_the_gripper_closes():
    """From the close command on, the arm's motion is zeroed for two steps and then while
    the fingers move; the gripper command passes; an operator's steps are only tracked,
    so a policy taking over a closed gripper is not held; Policy.act applies it only
    with grasp_hold."""
    move_open = np.array([0.01, 0.02, -0.01, 0.0, 0.0, 0.05, 0.0], np.float32)
    move_close = move_open.copy()
    move_close[-1] = 1.0
    state = lambda opening: np.array([0.3, 0.0, 0.2, opening])  # noqa: E731
    hold = HoldRule(settle=2)
    openings = [0.08, 0.08, 0.079, 0.06, 0.04, 0.031, 0.0308, 0.0308, 0.0308]
    commands = [move_open] + [move_close] * 8
    executed = [hold(state(o), a) for o, a in zip(openings, commands, strict=True)]
    moved = [bool(np.any(a[:6])) for a in executed]
    # onset and the next step held (settle), then while the fingers close by >= 0.5 mm
    assert moved == [True, False, False, False, False, False, True, True, True]
    assert all(a[-1] == c[-1] for a, c in zip(executed, commands, strict=True))
    hold.reset()
    for opening in (0.08, 0.06, 0.04, 0.031):  # the operator closes the gripper
        assert hold(state(opening), move_close, applies=False) is move_close
    assert np.any(hold(state(0.0308), move_close)[:6])  # the policy lifts at once

    config = PolicyConfig(kind="state", state_dim=4, env_dim=7)
    policy = Policy(config)
    policy.act_chunks = lambda *a, **k: move_close[None, None]
    observation = {"observation.state": state(0.08), "observation.environment_state": np.zeros(7)}
    assert not np.any(policy.act(observation, "")[:6])
    policy.config.grasp_hold = False
    policy.reset()
    assert np.array_equal(policy.act(observation, ""), move_close)


def test_the_gripper_is_commanded_open_or_closed_as_the_demonstrations_command_it():
    """binary_gripper (the default): a predicted gripper command between open and closed
    is sent as the nearer of the two (at GRIPPER_CLOSED), never as a half-closed gripper;
    off, as predicted. A checkpoint saved before the setting existed gets the default."""
    config = PolicyConfig(kind="state", state_dim=4, env_dim=7, grasp_hold=False)
    policy = Policy(config)
    observation = {"observation.state": np.zeros(4), "observation.environment_state": np.zeros(7)}
    for predicted, sent in ((0.3, 0.0), (0.49, 0.0), (0.5, 1.0), (0.8, 1.0)):
        action = np.array([0.01, 0.0, -0.01, 0.0, 0.0, 0.0, predicted], np.float32)
        policy.act_chunks = lambda *a, **k: action[None, None]  # noqa: B023
        policy.reset()
        acted = policy.act(observation, "")
        assert acted[-1] == sent and np.array_equal(acted[:6], action[:6])
    policy.config.binary_gripper = False
    policy.reset()
    assert policy.act(observation, "")[-1] == pytest.approx(0.8)
    saved = {k: v for k, v in asdict(config).items() if k != "binary_gripper"}
    assert PolicyConfig(**saved).binary_gripper


def test_the_image_policy_learns_to_locate_the_objects(dataset, tmp_path):
    """The auxiliary head says where the objects are relative to the TCP; SFT teaches it
    (the error falls), and 0 weight leaves the head out."""
    frames = load_frames([str(dataset)], cameras=["front", "wrist"], image_size=128)
    rows = np.arange(0, len(frames), 3)

    def locating_error(steps: int) -> float:
        out = tmp_path / f"vla_{steps}"
        result = train_sft(
            SFTConfig(datasets=[str(dataset)], out=str(out), policy="vla", steps=steps,
                      batch_size=16, log_every=1)
        )  # fmt: skip
        policy = Policy.from_pretrained(out)
        assert result.locating and policy.locates and policy.config.stem_stride == 4
        images = {c: frames.images[c][rows] for c in frames.images}
        instructions = [frames.instruction[r] for r in rows]
        batch = policy.inputs(frames.state[rows], None, images, instructions)
        targets = policy.locating_targets(frames.state[rows], frames.environment_state[rows])
        with torch.no_grad():
            return torch.nn.functional.mse_loss(policy.locate(batch), targets["objects"]).item()

    assert locating_error(80) < 0.5 * locating_error(1)
    plain = train_sft(
        SFTConfig(datasets=[str(dataset)], out=str(tmp_path / "plain"), policy="vla", steps=2,
                  batch_size=4, locate_weight=0.0, image_size=64)
    )  # fmt: skip
    policy = Policy.from_pretrained(plain.out)
    assert not plain.locating and not hasattr(policy, "locator") and policy.config.stem_stride == 2
    with pytest.raises(ValueError, match="no locating head"):
        policy.locate({})
    with pytest.raises(ValueError, match="image_size must be one of 64, 128, got 96"):
        SFTConfig(datasets=["d"], out="x", image_size=96)
    with pytest.raises(ValueError, match="locate_weight must be >= 0, got -1"):
        SFTConfig(datasets=["d"], out="x", locate_weight=-1)
    with pytest.raises(ValueError, match="locating the objects needs"):
        PolicyConfig(kind="vla", state_dim=8, locate_weight=1.0)
    with pytest.raises(ValueError, match="stem_stride must be one of"):
        PolicyConfig(kind="vla", state_dim=8, stem_stride=3)
    with pytest.raises(ValueError, match="locate_weight applies to the vla policy"):
        PolicyConfig(kind="state", state_dim=8, env_dim=7, locate_weight=1.0)


def test_locating_learns_from_the_datasets_that_hold_object_poses(dataset, tmp_path):
    """A real cell's demos without object poses mixed with the twin's: the image policy
    locates on the twin's frames only; the state policy, which reads poses, refuses."""
    episode = read_episode(Session(dataset.parent / "session").episode_paths()[0])
    del episode.data["observation.environment_state"]
    export_dataset([episode], tmp_path / "no_poses")
    frames = load_frames([str(dataset), str(tmp_path / "no_poses")])
    known = ~np.isnan(frames.environment_state).any(axis=1)
    assert not frames.environment_complete and known[frames.source == 0].all()
    assert not known[frames.source == 1].any()
    mixed = [str(dataset), str(tmp_path / "no_poses")]
    common = {"policy": "vla", "steps": 3, "batch_size": 8, "image_size": 64}
    result = train_sft(SFTConfig(datasets=mixed, out=str(tmp_path / "mixed"), **common))
    assert result.locating and np.isfinite(result.losses).all()
    alone = train_sft(
        SFTConfig(datasets=[str(tmp_path / "no_poses")], out=str(tmp_path / "alone"), **common)
    )
    assert not alone.locating and not Policy.from_pretrained(alone.out).locates
    with pytest.raises(ValueError, match="the state policy reads object poses"):
        train_sft(SFTConfig(datasets=mixed, out=str(tmp_path / "state"), policy="state"))
    assert not (tmp_path / "state").exists()


def test_a_128_pixel_image_costs_what_a_64_pixel_one_does_and_old_checkpoints_load(tmp_path):
    """The 8x8 stride-4 stem brings 128 px to the 32x32 maps that the 3x3 stride-2 stem
    makes of 64 px; a checkpoint saved before the stem and the locator existed loads as
    it was (stride 2, no locating head)."""
    wide = FiLMConvEncoder(stem_stride=4).blocks[0](torch.zeros(1, 3, 128, 128))
    narrow = FiLMConvEncoder(stem_stride=2).blocks[0](torch.zeros(1, 3, 64, 64))
    assert wide.shape == narrow.shape == (1, 32, 32, 32)
    saved = Policy(PolicyConfig(kind="vla", state_dim=6)).save_pretrained(tmp_path / "old")
    config = json.loads((saved / "config.json").read_text())
    for key in ("stem_stride", "locate_weight"):
        del config[key]
    (saved / "config.json").write_text(json.dumps(config))
    old = Policy.from_pretrained(saved)
    assert old.config.stem_stride == 2 and not old.locates


def test_resume_continues_exactly(dataset, tmp_path):
    common = {
        "datasets": [str(dataset)],
        "policy": "state",
        "batch_size": 32,
        "checkpoint_every": 20,
        "log_every": 10,
    }
    straight = train_sft(SFTConfig(out=str(tmp_path / "straight"), steps=40, **common))
    split = SFTConfig(out=str(tmp_path / "split"), steps=40, **common)
    with pytest.raises(KeyboardInterrupt):  # ten steps after the checkpoint at step 20
        train_sft(split, progress=_interrupt_at(30))
    resumed = train_sft(SFTConfig(out=str(tmp_path / "split"), **common), resume=True)
    assert resumed.losses == straight.losses  # the cosine went on where it stopped
    a, b = Policy.from_pretrained(tmp_path / "straight"), Policy.from_pretrained(tmp_path / "split")
    for key, value in a.state_dict().items():
        torch.testing.assert_close(value, b.state_dict()[key], rtol=0, atol=0)
    with pytest.raises(ValueError, match="already holds a run"):
        train_sft(SFTConfig(out=str(tmp_path / "straight"), steps=40, **common))
    with pytest.raises(ValueError, match="trained with `inputs` absolute, not relative"):
        train_sft(
            SFTConfig(out=str(tmp_path / "split"), steps=60, inputs="relative", **common),
            resume=True,
        )
    assert Policy.from_pretrained(tmp_path / "split").config.inputs == "absolute"


def _interrupt_at(stop: int):
    """An SFT progress callback that interrupts the run at step ``stop``."""

    def interrupt(step, metrics):
        if step == stop:
            raise KeyboardInterrupt

    return interrupt


def test_datasets_mix_by_frames_unless_weighted_and_a_resumed_run_keeps_its_weights(
    dataset, tmp_path
):
    one = read_episode(Session(dataset.parent / "session").episode_paths()[0])
    export_dataset([one], tmp_path / "one")
    mixed = [str(dataset), str(tmp_path / "one")]
    frames = load_frames(mixed)
    by_frames = np.bincount(frames.source) / len(frames.source)
    assert by_frames[0] > by_frames[1]  # two episodes against one

    def saved_weights(out):
        return torch.load(out / "training_state.pt", weights_only=False)["config"]["weights"]

    common = {"datasets": mixed, "policy": "state", "batch_size": 8}
    train_sft(SFTConfig(out=str(tmp_path / "default"), steps=2, **common))
    np.testing.assert_allclose(saved_weights(tmp_path / "default"), by_frames)
    train_sft(SFTConfig(out=str(tmp_path / "given"), steps=2, weights=[1, 3], **common))
    np.testing.assert_allclose(saved_weights(tmp_path / "given"), [0.25, 0.75])
    with pytest.raises(ValueError, match="was trained with `weights` 0.25,0.75"):
        train_sft(
            SFTConfig(out=str(tmp_path / "given"), steps=4, weights=[1, 1], **common), resume=True
        )
    assert train_sft(SFTConfig(out=str(tmp_path / "given"), **common), resume=True).steps == 2
    np.testing.assert_allclose(saved_weights(tmp_path / "given"), [0.25, 0.75])
    with pytest.raises(ValueError, match="trained on 2 datasets, not 1"):
        train_sft(
            SFTConfig(**common | {"datasets": mixed[:1]}, out=str(tmp_path / "given")), resume=True
        )
    # A run saved before the weights were recorded mixed its datasets equally.
    state = torch.load(tmp_path / "default" / "training_state.pt", weights_only=False)
    state["config"]["weights"] = None
    torch.save(state, tmp_path / "default" / "training_state.pt")
    train_sft(SFTConfig(out=str(tmp_path / "default"), steps=4, **common), resume=True)
    np.testing.assert_allclose(saved_weights(tmp_path / "default"), [0.5, 0.5])
    with pytest.raises(ValueError, match="weights needs 2 values"):
        train_sft(SFTConfig(out=str(tmp_path / "bad"), steps=2, weights=[1], **common))
    assert not (tmp_path / "bad").exists()


def test_a_resumed_run_keeps_its_own_learning_rate_and_batch_size(dataset, tmp_path):
    common = {"datasets": [str(dataset)], "policy": "state", "checkpoint_every": 4}
    own = {"lr": 3e-4, "batch_size": 16}
    straight = train_sft(SFTConfig(out=str(tmp_path / "straight"), steps=8, **common, **own))
    split = SFTConfig(out=str(tmp_path / "split"), steps=8, log_every=2, **common, **own)
    with pytest.raises(KeyboardInterrupt):
        train_sft(split, progress=_interrupt_at(6))
    resumed = train_sft(SFTConfig(out=str(tmp_path / "split"), **common), resume=True)
    assert resumed.losses == straight.losses
    with pytest.raises(ValueError, match="trained with `batch_size` 16, `lr` 0.0003; resume"):
        train_sft(
            SFTConfig(out=str(tmp_path / "split"), lr=1e-3, batch_size=8, **common), resume=True
        )


def test_the_learning_rate_decays_along_a_cosine_and_a_resumed_run_keeps_its_schedule(
    dataset, tmp_path
):
    config = SFTConfig(datasets=[], out="", policy="state", steps=100).resolved()
    assert config.lr_schedule == "cosine"
    assert SFTConfig(datasets=[], out="", policy="vla").resolved().lr_schedule == "constant"
    rates = [learning_rate(config, step) for step in (0, 50, 99)]
    assert rates[0] == config.lr and rates[1] == pytest.approx(config.lr / 2)
    assert 0 < rates[2] < 1e-3 * config.lr
    constant = replace(config, lr_schedule="constant")
    assert learning_rate(constant, 0) == learning_rate(constant, 99) == config.lr
    with pytest.raises(ValueError, match="lr_schedule must be one of cosine, constant"):
        SFTConfig(datasets=[], out="", lr_schedule="linear")
    common = {"datasets": [str(dataset)], "policy": "state", "batch_size": 8}
    out = tmp_path / "run"
    train_sft(SFTConfig(out=str(out), steps=2, **common))
    with pytest.raises(ValueError, match="trained with `lr_schedule` cosine"):
        train_sft(SFTConfig(out=str(out), steps=4, lr_schedule="constant", **common), resume=True)
    # A run saved before the schedule existed kept its rate constant, and goes on so.
    state = torch.load(out / "training_state.pt", weights_only=False)
    del state["config"]["lr_schedule"]
    torch.save(state, out / "training_state.pt")
    train_sft(SFTConfig(out=str(out), steps=4, **common), resume=True)
    saved = torch.load(out / "training_state.pt", weights_only=False)
    assert saved["config"]["lr_schedule"] == "constant"
    assert [g["lr"] for g in saved["optimizer"]["param_groups"]] == [config.lr]


def test_an_image_run_resumes_to_its_own_steps_and_names_every_option_that_differs(
    dataset, tmp_path
):
    common = {"datasets": [str(dataset)], "policy": "vla", "batch_size": 4, "image_size": 64}
    out = str(tmp_path / "vla")
    train_sft(SFTConfig(out=out, steps=4, **common))
    differ = f"`image_size` 64, `locate_weight` {SFTConfig.locate_weight}, not 128, 0.0"
    with pytest.raises(ValueError, match=differ):
        train_sft(
            SFTConfig(out=out, **common | {"image_size": 128}, locate_weight=0.0), resume=True
        )
    resumed = train_sft(SFTConfig(out=out, **common), resume=True)  # no --steps
    assert resumed.steps == 4  # the run's own steps, not the default 5000


def test_evaluation_writes_json_heatmap_and_episodes(tmp_path):
    report = evaluate(
        ExpertRunner(), "insert_hexagon", grid=(2, 4), out=tmp_path / "eval", world="plant"
    )
    saved = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert (
        set(saved) >= {"success_rate", "episodes", "cells"}
        and saved["episodes"] == report.episodes == 8
    )
    assert saved["success_rate"] == {"ID": 1.0, "OOD": 1.0}
    assert {c["region"] for c in saved["cells"]} == {"ID", "OOD"}
    assert (tmp_path / "eval" / "heatmap.png").stat().st_size > 5000
    episodes = [
        read_episode(p, images=False)
        for p in Session(tmp_path / "eval" / "session").episode_paths()
    ]
    assert {e.meta.source for e in episodes} == {"eval"} and all(
        e.meta.world == "plant" for e in episodes
    )
    assert all(c.region in ("ID", "OOD") for c in grid_cells("pick_place", (8, 8)))


def test_only_a_twin_evaluation_is_shared_between_workers(tmp_path):
    with pytest.raises(SettingError, match="workers shares the episodes in the twin only"):
        evaluate(ExpertRunner(), "pick_place", world="plant", workers=2, out=tmp_path / "eval")
    assert not (tmp_path / "eval").exists()


def test_runner_selection(state_checkpoint, tmp_path):
    assert isinstance(load_runner("expert"), ExpertRunner)
    assert load_runner(state_checkpoint).policy.config.temporal_ensemble == 0.01
    open_loop = load_runner(state_checkpoint, open_loop=True)
    assert open_loop.policy.config.temporal_ensemble is None
    assert open_loop.name.endswith(":open-loop")  # its evaluations are told apart
    with pytest.raises(ValueError, match="is not a policy checkpoint"):
        load_runner(tmp_path)
    with pytest.raises(ValueError, match="open_loop applies to a twinrl checkpoint"):
        load_runner("expert", open_loop=True)


def test_evaluation_leaves_the_callers_random_stream_alone(state_checkpoint, tmp_path):
    """A runner re-seeds torch per episode; training that evaluates (real RL, mining)
    must draw the same noise afterwards whatever the evaluation did."""
    runner = TwinrlRunner(state_checkpoint)
    torch.manual_seed(123)
    expected = torch.rand(4)
    torch.manual_seed(123)
    evaluate(runner, "pick_place", grid=(1, 2), out=tmp_path / "eval")
    assert torch.equal(torch.rand(4), expected)


def test_training_augmentation_shifts_images_and_noises_states_without_touching_the_batch():
    policy = Policy(PolicyConfig(kind="vla", state_dim=6, cameras=["front"]))
    images = torch.rand(64, 3, 32, 32)
    batch = {"state": torch.zeros(64, 6), "image.front": images.clone()}
    augmented = policy.augment(batch, torch.Generator().manual_seed(0))
    assert torch.equal(batch["image.front"], images) and not batch["state"].any()
    assert augmented["state"].std().item() == pytest.approx(STATE_NOISE, rel=0.15)
    # Each image is a crop of its replicate-padded self shifted by at most IMAGE_SHIFT px.
    padded = torch.nn.functional.pad(images, (IMAGE_SHIFT,) * 4, mode="replicate")
    offsets = [(dy, dx) for dy in range(2 * IMAGE_SHIFT + 1) for dx in range(2 * IMAGE_SHIFT + 1)]
    shifts = []
    for i, image in enumerate(augmented["image.front"]):
        found = [
            o
            for o in offsets
            if torch.equal(image, padded[i, :, o[0] : o[0] + 32, o[1] : o[1] + 32])
        ]
        assert found, f"image {i} is not a shifted crop"
        shifts.append(found[0])
    assert len(set(shifts)) > 10  # the shift is drawn per image


def test_fit_look_gives_the_twin_the_plants_appearance(tmp_path):
    from twinrl_learn.studies.table1 import fit_look, record_real_demos
    from twinrl_robot.plant import DEFAULT_EFFECTS_FILE
    from twinrl_sim.effects import load_effects
    from twinrl_sim.spec import load_spec

    record_real_demos("pick_place", 2, tmp_path / "plant", seed=1)
    scene = fit_look("pick_place", tmp_path / "plant" / "real", tmp_path / "fitted.yaml")
    truth = load_effects(DEFAULT_EFFECTS_FILE)["appearance"]
    fitted = scene.effects["appearance"]
    assert fitted["light_scale"] == pytest.approx(truth["light_scale"], abs=0.04)
    np.testing.assert_allclose(fitted["table_tint"], truth["table_tint"], atol=0.01)
    assert load_spec(tmp_path / "fitted.yaml").effects == scene.effects
    # A cell that looks like the twin gives nothing to fit, and says so.
    (tmp_path / "physics_only.yaml").write_text("object_friction: {sliding: 0.7}\n")
    record_real_demos(
        "pick_place", 2, tmp_path / "same", seed=1, effects=tmp_path / "physics_only.yaml"
    )
    with pytest.raises(RuntimeError, match="name no appearance difference"):
        fit_look("pick_place", tmp_path / "same" / "real", tmp_path / "not_written.yaml")
    assert not (tmp_path / "not_written.yaml").exists()


def test_the_table_i_benchmark_end_to_end_at_smoke_scale(tmp_path):
    from twinrl_learn.studies.table1 import MIXES

    out = tmp_path / "stage1"
    smoke = ["--grid", "2x2", "--episodes", "1", "--state-steps", "40", "--detours", "1"]
    rows = stage1_smoke(out, *smoke)
    assert [(r["twin_id"], r["twin_ood"]) for r in rows] == list(MIXES)
    assert all(set(r["success"]) == {"ID", "OOD"} for r in rows)
    table = (out / "table1.md").read_text()
    assert "100 % of them straying beside the object first" in table
    assert table.count("| pick_place | state (privileged) |") == len(MIXES)
    assert "true object poses, which only the twin and the plant know" in table
    for r in rows:
        name = f"state_real_id{r['twin_id']}_ood{r['twin_ood']}"
        assert (out / "pick_place" / f"{name}_eval" / "heatmap.png").is_file()
    twin = Session(out / "pick_place" / "twin_ood" / "session").episode_paths()
    assert {read_episode(p, images=False).meta.policy for p in twin} == {"synthesis:plan+detour"}


TRAINER = """
    import sys
    from twinrl_learn.settings import SFTConfig
    from twinrl_learn.sft import train_sft
    config = SFTConfig(datasets=[sys.argv[1]], out=sys.argv[2], policy="state", steps=400,
                       batch_size=16, checkpoint_every=7, log_every=1)
    train_sft(config, progress=lambda step, metrics: print(step, flush=True))
"""


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.long)])
def test_training_killed_at_a_random_step_resumes(dataset, tmp_path, seed):
    """SIGKILL at a seeded random step (possibly mid-checkpoint): the run resumes from its
    last whole checkpoint and finishes."""
    import signal
    import subprocess
    import sys
    import textwrap

    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(TRAINER), str(dataset), str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    stop = int(np.random.default_rng(seed).integers(8, 60))
    for line in proc.stdout:
        if int(line) >= stop:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    common = {"datasets": [str(dataset)], "policy": "state", "batch_size": 16}
    resumed = train_sft(SFTConfig(out=str(out), checkpoint_every=7, **common), resume=True)
    assert resumed.steps == 400
    Policy.from_pretrained(out)
