"""Policies behind one ``act(observation) -> action`` interface for evaluation.

- :class:`TwinrlRunner`: a twinrl checkpoint (``Policy.from_pretrained``);
- :class:`LeRobotRunner`: any lerobot policy checkpoint (ACT, Diffusion, SmolVLA, ...),
  with lerobot's own pre/post-processors (normalisation, tokenisation);
- :class:`ExpertRunner`: the task's scripted expert (a reference for the evaluation).

``load_runner(path_or_name)`` picks the right one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from twinrl_data.errors import SettingError
from twinrl_learn.compute import resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.policy import Policy, is_checkpoint
from twinrl_sim.tasks import Task, TaskConfig


class Runner(Protocol):
    """Acts in episodes: ``reset`` at each start, ``act`` at each control step."""

    name: str
    needs_images: bool
    cameras: tuple[str, ...]

    def reset(self, task: Task, config: TaskConfig, seed: int) -> None: ...

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray: ...


class RunnerSource:
    """A runner as the robot loop's action source for one episode, seeded with ``seed``."""

    def __init__(self, runner: Runner, seed: int) -> None:
        self.runner, self.seed = runner, seed

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.runner.reset(task, config, seed=self.seed)

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        return np.asarray(self.runner.act(observation), np.float32)

    def interrupted(self) -> None:
        """Evaluations run without an operator; nothing to forget."""


class TwinrlRunner:
    """A twinrl policy: a checkpoint folder, or a policy in memory (``name`` then
    labels its episodes) such as the one an RL run is training."""

    def __init__(
        self, policy: str | Path | Policy, name: str | None = None, device: str = "cpu"
    ) -> None:
        if isinstance(policy, Policy):
            self.policy = policy
            self.name = name or "twinrl:in-memory"
        else:
            self.policy = Policy.from_pretrained(policy, device)
            self.name = name or f"twinrl:{Path(policy).name}"
        self.needs_images = self.policy.needs_images
        self.cameras = tuple(self.policy.config.cameras) if self.needs_images else ()
        self._instruction = ""

    def reset(self, task: Task, config: TaskConfig, seed: int) -> None:
        self._instruction = task.instruction
        self.policy.reset()
        torch.manual_seed(seed)

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        return self.policy.act(observation, self._instruction)


class ExpertRunner:
    """The scripted expert: privileged state; an upper reference for evaluations."""

    name = "expert"
    needs_images = False
    cameras = ()

    def __init__(self) -> None:
        self._expert = None

    def reset(self, task: Task, config: TaskConfig, seed: int) -> None:
        self._expert = task.expert(config, np.random.default_rng(seed))

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        return self._expert.act(observation)


class LeRobotRunner:
    """A lerobot policy checkpoint (the ``pretrained_model`` folder lerobot-train writes)."""

    def __init__(self, path: str | Path, device: str = "cpu") -> None:
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        path = Path(path)
        config = PreTrainedConfig.from_pretrained(path)
        config.device = str(resolve_device(device))  # lerobot reads a concrete one
        policy_class = get_policy_class(config.type)
        self.policy = policy_class.from_pretrained(path, config=config)
        self.policy.eval()
        # The processors keep the device they were trained on: run them where the policy runs,
        # so that a checkpoint trained on a GPU acts on a machine without one.
        self.pre, self.post = make_pre_post_processors(
            config,
            pretrained_path=str(path),
            preprocessor_overrides={"device_processor": {"device": config.device}},
        )
        self.name = f"lerobot:{config.type}"
        self.input_features = dict(config.input_features)
        self.cameras = tuple(
            k.removeprefix("observation.images.")
            for k in self.input_features
            if k.startswith("observation.images.")
        )
        self.needs_images = bool(self.cameras)
        self._instruction = ""

    def reset(self, task: Task, config: TaskConfig, seed: int) -> None:
        self._instruction = task.instruction
        self.policy.reset()
        torch.manual_seed(seed)

    @torch.no_grad()
    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        batch: dict[str, Any] = {"task": [self._instruction]}
        for key in self.input_features:
            value = np.asarray(observation[key])
            if key.startswith("observation.images."):
                batch[key] = torch.from_numpy(value).permute(2, 0, 1)[None].float() / 255.0
            else:
                batch[key] = torch.from_numpy(value.astype(np.float32))[None]
        action = self.post(self.policy.select_action(self.pre(batch)))
        return np.asarray(action[0].cpu().numpy(), np.float32)


def load_runner(
    spec: str | Path,
    *,
    open_loop: bool = False,
    grasp_hold: bool | None = None,
    binary_gripper: bool | None = None,
    close_as_demonstrated: bool | None = None,
    device: str = "cpu",
) -> Runner:
    """``expert``, a twinrl checkpoint folder, or a lerobot ``pretrained_model`` folder,
    its network on ``device`` (auto, cpu, cuda or cuda:N).
    ``open_loop`` runs a twinrl policy's action chunks open-loop instead of averaging
    its predictions for each step (``PolicyConfig.temporal_ensemble``); ``grasp_hold``
    turns the arm's hold while the gripper closes on or off, ``binary_gripper`` the
    gripper commanded open or closed rather than as predicted, and
    ``close_as_demonstrated`` a close held until the tool is as low as the
    demonstrations close (``None``: as the checkpoint says; the ``PolicyConfig`` fields
    of those names)."""
    device = str(resolve_device(device))  # a bad name is refused whatever the policy
    path = Path(spec)
    asked_for = (
        (open_loop, "open_loop"),
        (grasp_hold is not None, "grasp_hold"),
        (binary_gripper is not None, "binary_gripper"),
        (close_as_demonstrated is not None, "close_as_demonstrated"),
    )
    for asked, setting in asked_for:
        if asked and not is_checkpoint(path):
            raise SettingError(
                setting,
                f"applies to a twinrl checkpoint, not {spec} (the expert acts step by "
                "step, and a lerobot policy acts as its own config says)",
            )
    if str(spec) == "expert":
        return ExpertRunner()
    if is_checkpoint(path):
        runner = TwinrlRunner(path, device=device)
        config = runner.policy.config
        # Named apart: mining reuses logged evaluations of a policy by its name.
        if open_loop:
            runner.name += ":open-loop"
            config.temporal_ensemble = None
        if grasp_hold is not None and grasp_hold != config.grasp_hold:
            runner.name += ":hold" if grasp_hold else ":no-hold"
            config.grasp_hold = grasp_hold
        if binary_gripper is not None and binary_gripper != config.binary_gripper:
            runner.name += ":binary-gripper" if binary_gripper else ":as-predicted-gripper"
            config.binary_gripper = binary_gripper
        if close_as_demonstrated is not None and (
            close_as_demonstrated != config.close_as_demonstrated
        ):
            runner.name += ":close-low" if close_as_demonstrated else ":close-as-predicted"
            config.close_as_demonstrated = close_as_demonstrated
        return runner
    if (path / "config.json").is_file() and "type" in json.loads(
        (path / "config.json").read_text()
    ):
        return LeRobotRunner(path, device)
    raise LearnError(
        f"{path} is not a policy checkpoint: give a twinrl SFT output folder, a lerobot "
        "pretrained_model folder, or 'expert'"
    )
