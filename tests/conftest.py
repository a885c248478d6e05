"""Shared fixtures. Rendering is headless (EGL) in tests."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from twinrl_sim.tasks import TASKS

TASK_NAMES = list(TASKS)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def expert_commands(env, config, seed: int = 0, steps: int = 40):
    """Run the scripted expert from ``config``; return (joint targets, gripper commands)."""
    expert = env.task.expert(config, np.random.default_rng(seed))
    obs, _ = env.reset(options={"config": config})
    targets, gripper = [], []
    for _ in range(steps):
        action = expert.act(obs)
        obs, *_, info = env.step(action)
        targets.append(info["command.joint_target"])
        gripper.append(action[6])
    return np.array(targets, float), np.array(gripper, float)


def record_demos(
    folder, task: str = "pick_place", episodes: int = 1, seed: int = 0, world: str = "twin"
):
    """Record scripted-expert demos in ``world`` (the twin by default) into
    ``folder/session`` and export them as the LeRobotDataset ``folder/dataset``; returns
    the dataset's path."""
    from twinrl_data.lerobot_io import export_dataset
    from twinrl_data.mcap_log import read_episode
    from twinrl_data.session import Session
    from twinrl_robot.scripted import run_scripted_expert

    session = Session.create(folder / "session")
    run_scripted_expert(task, world=world, episodes=episodes, session=session, seed=seed)
    export_dataset((read_episode(p) for p in session.episode_paths()), folder / "dataset")
    return folder / "dataset"


def tiny_state_policy(folder, *, seed: int, steps: int):
    """Expert demos (``folder/dataset``) and a state policy briefly trained on them
    (``folder/sft``, chunks of 4); returns both paths."""
    from twinrl_learn.settings import SFTConfig
    from twinrl_learn.sft import train_sft

    dataset = record_demos(folder, seed=seed)
    train_sft(
        SFTConfig(
            datasets=[str(dataset)],
            out=str(folder / "sft"),
            policy="state",
            steps=steps,
            batch_size=16,
            chunk=4,
        )
    )
    return dataset, folder / "sft"


def stage1_smoke(out, *options: str) -> list[dict]:
    """``twinrl bench stage1`` on pick_place at a tenth of its demos into ``out``, with
    ``options``; it must succeed. Returns the rows of its ``stage1.json``."""
    import json

    from typer.testing import CliRunner

    from twinrl_learn.cli import app

    args = ["bench", "stage1", "--out", str(out), "--tasks", "pick_place", "--scale", "0.1"]
    result = CliRunner().invoke(app, [*args, *options])
    assert result.exit_code == 0, result.output
    return json.loads((out / "stage1.json").read_text())["rows"]


def lerobot_train(dataset, output_dir, *options: str):
    """Run lerobot's own trainer offline: a few ACT steps on ``dataset``."""
    import os
    import subprocess
    import sys

    trainer = os.path.join(os.path.dirname(sys.executable), "lerobot-train")
    return subprocess.run(
        [
            trainer,
            f"--dataset.repo_id=tests/{dataset.name}",
            f"--dataset.root={dataset}",
            "--dataset.video_backend=pyav",
            "--policy.type=act",
            "--policy.device=cpu",
            "--policy.push_to_hub=false",
            "--policy.pretrained_backbone_weights=null",
            "--steps=2",
            "--batch_size=2",
            "--num_workers=0",
            f"--output_dir={output_dir}",
            "--wandb.enable=false",
            *options,
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )
