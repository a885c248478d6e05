"""lerobot's own policies, trained by lerobot's own trainer on twinrl's datasets.

They are Table I's external anchor (``twinrl bench stage1 --policies act``): the same
episodes, learned by a policy and a recipe twinrl did not write. A lerobot policy reads
every ``observation.*`` column it is given, so :func:`policy_dataset` first removes what
a real cell does not see (``observation.environment_state``: the object poses only the
twin and the plant know) and the columns one source logs and another does not (the
plant's ``observation.effort``, the twin's ``action.policy``), then merges the sources
with lerobot's own dataset tools. lerobot's trainer samples every frame alike, so each
source weighs what its frames number.

:func:`train_lerobot_policy` runs ``lerobot-train`` in a process of its own and returns
the ``pretrained_model`` folder, which ``twinrl eval`` and
:class:`~twinrl_learn.runners.LeRobotRunner` act with. ACT's recipe here: chunks of 10
actions predicted every step and averaged over time (its temporal ensemble; a 10 Hz arm
needs no longer chunk), a ResNet-18 trained from scratch (lerobot would download
ImageNet weights), batch 16. On 2 CPU cores a step takes about 5 s; on one H200 GPU 60 ms.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from twinrl_data.lerobot_io import VIDEO_BACKEND
from twinrl_learn.compute import check_device, resolve_device
from twinrl_learn.errors import LearnError

NOT_SEEN_BY_A_CELL = ("observation.environment_state",)
"""Columns a real cell cannot fill: the true object poses."""
NOT_IN_EVERY_SOURCE = ("observation.effort", "action.policy")
"""Columns the plant logs and the twin does not, or the other way round."""
LEROBOT_POLICIES = {
    "act": (
        "--policy.chunk_size=10",
        "--policy.n_action_steps=1",
        "--policy.temporal_ensemble_coeff=0.01",
        "--policy.pretrained_backbone_weights=null",
    ),
}
"""lerobot's policies twinrl trains, with the options of their recipe here."""


@dataclass(frozen=True)
class LeRobotTraining:
    """How one lerobot policy is trained."""

    policy: str = "act"
    steps: int = 3000
    batch_size: int = 16
    seed: int = 0
    device: str = "auto"

    def __post_init__(self) -> None:
        if self.policy not in LEROBOT_POLICIES:
            raise LearnError(
                f"lerobot policy '{self.policy}' is not trained here; use one of "
                f"{', '.join(LEROBOT_POLICIES)}"
            )
        if self.steps < 1 or self.batch_size < 1:
            raise LearnError("lerobot training needs at least 1 step and a batch of 1")
        check_device(self.device)


def policy_dataset(datasets: Sequence[str | Path], out: str | Path) -> Path:
    """``datasets`` (twinrl LeRobotDatasets) as one dataset at ``out`` that a lerobot
    policy may learn from: the columns a cell cannot fill, or that not every source has,
    removed; the sources merged in order. Returns ``out``."""
    from lerobot.datasets import LeRobotDataset
    from lerobot.datasets.dataset_tools import merge_datasets, remove_feature

    out = Path(out)
    if out.exists():
        raise LearnError(f"{out} exists; choose another folder for the policy's dataset")
    if not datasets:
        raise LearnError("no dataset to train a lerobot policy on")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as scratch:
        sources = []
        for index, root in enumerate(datasets):
            source = LeRobotDataset(f"twinrl/source{index}", root=root, video_backend=VIDEO_BACKEND)
            drop = [
                f for f in NOT_SEEN_BY_A_CELL + NOT_IN_EVERY_SOURCE if f in source.meta.features
            ]
            if drop:
                source = remove_feature(
                    source, drop, output_dir=Path(scratch) / str(index), repo_id=f"twinrl/{index}"
                )
            sources.append(source)
        merge_datasets(sources, output_repo_id="twinrl/policy_dataset", output_dir=out)
    return out


def train_lerobot_policy(dataset: str | Path, out: str | Path, training: LeRobotTraining) -> Path:
    """Train ``training.policy`` on ``dataset`` with lerobot's trainer, its run in
    ``out`` (its log in ``out.log``); returns the ``pretrained_model`` folder."""
    out = Path(out)
    if out.exists():
        raise LearnError(f"{out} exists; lerobot's trainer starts a run in a new folder")
    device = resolve_device(training.device)
    command = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_train",
        f"--dataset.repo_id=twinrl/{Path(dataset).name}",
        f"--dataset.root={dataset}",
        f"--dataset.video_backend={VIDEO_BACKEND}",
        f"--policy.type={training.policy}",
        f"--policy.device={device.type}",
        "--policy.push_to_hub=false",
        *LEROBOT_POLICIES[training.policy],
        f"--steps={training.steps}",
        f"--save_freq={training.steps}",
        f"--batch_size={training.batch_size}",
        f"--seed={training.seed}",
        f"--num_workers={min(4, os.cpu_count() or 1)}",
        f"--output_dir={out}",
        "--wandb.enable=false",
    ]
    log = out.with_name(out.name + ".log")
    environment = {**os.environ, "HF_HUB_OFFLINE": "1"}  # the dataset is here, nothing to fetch
    with log.open("w") as stream:
        done = subprocess.run(command, stdout=stream, stderr=subprocess.STDOUT, env=environment)
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    if done.returncode != 0 or not checkpoint.is_dir():
        raise LearnError(
            f"lerobot's trainer stopped (exit {done.returncode}) before saving {training.policy}; "
            f"its last lines are in {log}"
        )
    return checkpoint
