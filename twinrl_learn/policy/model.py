"""The policy itself: the networks, the action distribution and the losses, behind the
interface every learner and runner uses; inputs, normalisation, augmentation, acting
and checkpoints are their own modules of this package."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from twinrl_learn.compute import module_device, resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.language import EMBEDDING_DIM, InstructionCache
from twinrl_learn.policy.acting import ChunkedActing
from twinrl_learn.policy.augmentation import augment
from twinrl_learn.policy.checkpoint import load_checkpoint, save_checkpoint
from twinrl_learn.policy.config import EPS, LOG_STD_RANGE, PolicyConfig
from twinrl_learn.policy.inputs import InputEncoder
from twinrl_learn.policy.networks import FiLMConvEncoder
from twinrl_learn.policy.normalization import Normalizer


class Policy(nn.Module):
    """See the module docstring. ``forward`` works on normalised tensors; :meth:`act`
    takes one observation dict of the episode contract and returns a physical action."""

    def __init__(self, config: PolicyConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.encoders = nn.ModuleDict()
        self.estimator = None
        features = 0
        if self.perceives:
            from twinrl_learn.perception.estimator import EstimatorConfig, PoseEstimator

            self.estimator = PoseEstimator(EstimatorConfig(**c.estimator))
            self.estimator.requires_grad_(False)
            proprio = self.state_width + self.estimator.config.output_dim
        elif c.kind == "vla":
            for camera in c.cameras:
                self.encoders[camera] = FiLMConvEncoder(stem_stride=c.stem_stride)
                features += self.encoders[camera].out_dim
            proprio = self.state_width
        else:
            proprio = self.privileged_width
        self.proprio = nn.Sequential(
            nn.Linear(proprio, c.hidden), nn.LayerNorm(c.hidden), nn.ReLU()
        )
        self.trunk = nn.Sequential(
            nn.Linear(features + c.hidden + EMBEDDING_DIM, c.hidden),
            nn.ReLU(),
            nn.Linear(c.hidden, c.hidden),
            nn.ReLU(),
        )
        self.head = nn.Linear(c.hidden, 2 * c.chunk * c.action_dim)
        if self.locates:
            self.locator = nn.Linear(c.hidden, 3 * len(c.object_indices))
        self.instructions = InstructionCache(c.instructions)
        self.normalizer = Normalizer(c.stats, c.state_inputs)
        self.input_encoder = InputEncoder(c, self.normalizer, self.instructions, self.estimator)
        self.acting = ChunkedActing(c)

    @property
    def perceives(self) -> bool:
        """Whether the image policy acts through a pose estimator
        (:mod:`twinrl_learn.perception`) rather than its own image encoders."""
        return self.config.kind == "vla" and self.config.estimator is not None

    @property
    def encodes_images(self) -> bool:
        """Whether the policy has image encoders of its own (the image policy that does
        not act through a pose estimator)."""
        return self.config.kind == "vla" and not self.perceives

    @property
    def locates(self) -> bool:
        """Whether the image policy has the auxiliary head that locates the objects."""
        return self.config.kind == "vla" and self.config.locate_weight > 0

    @property
    def device(self) -> torch.device:
        """Where the policy's weights live; :meth:`inputs` builds its batches there."""
        return module_device(self)

    @property
    def state_width(self) -> int:
        return len(self.config.state_inputs) or self.config.state_dim

    @property
    def relative_width(self) -> int:
        """Per object: a position offset (3), plus a relative orientation (6) if relative."""
        per_object = 9 if self.config.inputs == "relative" else 3
        return per_object * len(self.config.object_indices)

    @property
    def privileged_width(self) -> int:
        """Width of the state policy's input vector (:meth:`privileged_inputs`)."""
        absolute = self.config.env_dim if self.config.inputs == "absolute" else 0
        return self.state_width + absolute + self.relative_width

    def privileged_inputs(self, batch: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """What the state policy reads of a normalised batch (and an image policy that
        perceives: the estimated poses in place of the true ones)."""
        if self.config.inputs == "relative" or self.perceives:
            return [batch["state"], batch["relative"]]
        return [batch["state"], batch["env"], batch["relative"]]

    # ------------------------------------------------------------------ core
    def keypoints(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """The image encoders' keypoints of a normalised batch, every camera's in turn
        (None for the state policy). They are most of an image policy's cost, so an RL
        update computes them once per batch and hands them to :meth:`features` and
        :meth:`critic_inputs`."""
        if not self.encodes_images:
            return None
        text = batch["text"]
        return torch.cat(
            [encoder(batch[f"image.{camera}"], text) for camera, encoder in self.encoders.items()],
            dim=-1,
        )

    def features(
        self, batch: dict[str, torch.Tensor], keypoints: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Trunk features of a normalised batch (``keypoints``: the batch's
        :meth:`keypoints`, when already computed)."""
        if self.encodes_images:
            keypoints = self.keypoints(batch) if keypoints is None else keypoints
            parts = [keypoints, self.proprio(batch["state"])]
        else:
            parts = [self.proprio(torch.cat(self.privileged_inputs(batch), dim=-1))]
        parts.append(batch["text"])
        return self.trunk(torch.cat(parts, dim=-1))

    def critic_inputs(
        self, batch: dict[str, torch.Tensor], keypoints: torch.Tensor | None = None
    ) -> torch.Tensor:
        """What a critic reads: the image encoders' keypoints (no gradient: the critic
        sits on frozen encoder features, as in TwinRL) or the privileged state, plus
        proprio and the instruction embedding (``keypoints``: as for :meth:`features`)."""
        if self.encodes_images:
            if keypoints is None:
                with torch.no_grad():
                    keypoints = self.keypoints(batch)
            parts = [keypoints.detach(), batch["state"]]
        else:
            parts = self.privileged_inputs(batch)
        return torch.cat([*parts, batch["text"]], dim=-1)

    @property
    def critic_input_dim(self) -> int:
        c = self.config
        if self.perceives:
            width = self.state_width + self.estimator.config.output_dim
        elif c.kind == "vla":
            width = sum(e.out_dim for e in self.encoders.values()) + self.state_width
        else:
            width = self.privileged_width
        return width + EMBEDDING_DIM

    def distribution(
        self, batch: dict[str, torch.Tensor], features: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the pre-tanh Gaussian, shape (B, chunk, action_dim)
        (``features``: the batch's trunk features, when already computed)."""
        features = self.features(batch) if features is None else features
        # float32 from here on: under a GPU's bfloat16 autocast the log-likelihood
        # would otherwise be computed to three digits.
        out = self.head(features).float().view(-1, self.config.chunk, 2, self.config.action_dim)
        mean, log_std = out[:, :, 0], out[:, :, 1].clamp(*LOG_STD_RANGE)
        return mean, log_std

    def _log_prob_terms(
        self,
        batch: dict[str, torch.Tensor],
        actions: torch.Tensor,
        features: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.distribution(batch, features)
        clipped = actions.clamp(-1 + EPS, 1 - EPS)
        pre_tanh = torch.atanh(clipped)
        z = (pre_tanh - mean) / log_std.exp()
        normal = -0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi)
        return normal - torch.log(1 - clipped**2 + 1e-6), log_std

    def log_prob(self, batch: dict[str, torch.Tensor], actions: torch.Tensor) -> torch.Tensor:
        """log pi(a|s) of normalised actions in (-1, 1) under the tanh-squashed Gaussian."""
        terms, _ = self._log_prob_terms(batch, actions)
        return terms.sum(dim=(-1, -2))

    def imitation_loss(
        self,
        batch: dict[str, torch.Tensor],
        actions: torch.Tensor,
        beta: float = 1.0,
        features: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """L_IL = -E[log pi(a|s)], each term weighted by sigma^(2 beta) (beta-NLL).

        Plain NLL lets the learned spread decide how closely the mean is fitted, and a
        policy then stops short of its targets; beta = 1 gives the mean the gradients of
        a squared error while the spread is still learned (Seitzer et al., 2022).
        """
        terms, log_std = self._log_prob_terms(batch, actions, features)
        weight = torch.exp(2 * beta * log_std).detach()
        return -(weight * terms).sum(dim=(-1, -2)).mean()

    def sft_loss(self, batch: dict[str, torch.Tensor], actions: torch.Tensor) -> torch.Tensor:
        """What SFT minimises: the imitation loss, plus ``locate_weight`` times the
        locating loss on the rows whose true object offsets the batch holds
        (:meth:`locating_targets`)."""
        features = self.features(batch)
        loss = self.imitation_loss(batch, actions, features=features)
        known = batch.get("objects_known")
        if self.locates and known is not None and bool(known.any()):
            located = self.locator(features[known]).float()
            loss = loss + self.config.locate_weight * F.mse_loss(located, batch["objects"][known])
        return loss

    def locating_targets(
        self, state: np.ndarray, environment_state: np.ndarray
    ) -> dict[str, torch.Tensor]:
        """The locating head's targets for raw rows: ``objects``, each object's offset
        from the TCP (:meth:`relative_poses`), and ``objects_known``, the rows whose
        environment state is not NaN (:class:`~twinrl_data.training.FrameTable`)."""
        env = torch.as_tensor(np.asarray(environment_state, np.float32))
        known = ~torch.isnan(env).any(dim=-1)
        state = torch.as_tensor(np.asarray(state, np.float32))
        return {
            "objects": self.relative_poses(state, torch.nan_to_num(env)).to(self.device),
            "objects_known": known.to(self.device),
        }

    def locate(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Where the image policy sees each object relative to the TCP: (B, 3 x objects)
        in decimetres along the base axes, the scale of :meth:`relative_poses`."""
        if not self.locates:
            raise LearnError("this policy has no locating head (trained with locate_weight 0)")
        return self.locator(self.features(batch)).float()

    def rsample(
        self, batch: dict[str, torch.Tensor], features: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised normalised actions (B, chunk, A) and their log-probabilities (B)
        (``features``: the batch's trunk features, when already computed)."""
        mean, log_std = self.distribution(batch, features)
        pre_tanh = mean + log_std.exp() * torch.randn_like(mean)
        actions = torch.tanh(pre_tanh)
        z = (pre_tanh - mean) / log_std.exp()
        log_prob = -0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi)
        log_prob = log_prob - torch.log(1 - actions.pow(2) + 1e-6)
        return actions, log_prob.sum(dim=(-1, -2))

    def sample(
        self,
        batch: dict[str, torch.Tensor],
        deterministic: bool = False,
        std_scale: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Normalised actions: the mode, or a draw with the spread scaled by ``std_scale``
        (from ``generator``, or torch's global stream when ``None``)."""
        mean, log_std = self.distribution(batch)
        if deterministic:
            return torch.tanh(mean)
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype).to(mean.device)
        return torch.tanh(mean + std_scale * log_std.exp() * noise)

    # --------------------------------------------- inputs (see policy.inputs)
    def normalize(self, key: str, values: torch.Tensor) -> torch.Tensor:
        """See :meth:`Normalizer.normalize`."""
        return self.normalizer.normalize(key, values)

    def unnormalize_action(self, values: torch.Tensor) -> torch.Tensor:
        """See :meth:`Normalizer.unnormalize_action`."""
        return self.normalizer.unnormalize_action(values)

    def relative_poses(self, state: torch.Tensor, env: torch.Tensor) -> torch.Tensor:
        """See :meth:`InputEncoder.relative_poses`."""
        return self.input_encoder.relative_poses(state, env)

    def inputs(
        self,
        state: np.ndarray | torch.Tensor,
        environment_state: np.ndarray | torch.Tensor | None,
        images: dict[str, np.ndarray | torch.Tensor],
        instructions: list[str],
        estimates: np.ndarray | torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """A normalised input batch from raw arrays (B rows) on the policy's device: what
        :meth:`features` reads (``estimates``: see :meth:`InputEncoder.inputs`)."""
        batch = self.input_encoder.inputs(state, environment_state, images, instructions, estimates)
        device = self.device
        return {key: value.to(device, non_blocking=True) for key, value in batch.items()}

    def augment(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator
    ) -> dict[str, torch.Tensor]:
        """A training copy of a normalised batch (see :func:`augmentation.augment`)."""
        return augment(batch, self.config, generator)

    def observation_inputs(
        self, observations: dict[str, Any], instructions: list[str]
    ) -> dict[str, torch.Tensor]:
        """:meth:`inputs` from a batch of contract observations (leading batch axis)."""
        images = {}
        if self.needs_images:
            images = {
                c: np.asarray(observations[f"observation.images.{c}"]) for c in self.config.cameras
            }
        return self.inputs(
            observations["observation.state"],
            observations.get("observation.environment_state"),
            images,
            instructions,
        )

    @torch.no_grad()
    def act_chunks(
        self,
        observations: dict[str, Any],
        instructions: list[str],
        deterministic: bool = True,
        std_scale: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> np.ndarray:
        """Action chunks (B, chunk, A) in physical units for a batch of observations
        (sampled from ``generator`` unless ``deterministic``; see :meth:`sample`)."""
        batch = self.observation_inputs(observations, instructions)
        actions = self.sample(batch, deterministic, std_scale, generator)
        return self.unnormalize_action(actions.float().cpu()).numpy().astype(np.float32)

    def act(
        self, observation: dict[str, Any], instruction: str, deterministic: bool = True
    ) -> np.ndarray:
        """The next action (physical units) for one observation of the episode contract,
        from the chunks predicted so far (see :mod:`twinrl_learn.policy.acting`);
        :meth:`reset` starts afresh."""
        return self.acting.act(
            observation,
            lambda batch: self.act_chunks(batch, [instruction], deterministic)[0],
            self.object_offsets if self.perceives_objects else None,
        )

    @property
    def perceives_objects(self) -> bool:
        """Whether the policy knows where the objects are relative to the tool when it
        acts: the state policy (privileged poses) and an image policy acting through a
        pose estimator."""
        return self.perceives or (self.config.kind == "state" and self.config.tcp_index >= 0)

    @torch.no_grad()
    def object_offsets(self, observation: dict[str, Any]) -> np.ndarray:
        """Each object's position minus the TCP's (objects, 3; m, base axes) in one
        contract observation, as the policy perceives it: the pose estimator's estimate
        for an image policy, the logged poses for the state policy."""
        state = np.asarray(observation["observation.state"], np.float32)[None]
        if self.perceives:
            images = {
                c: np.asarray(observation[f"observation.images.{c}"])[None]
                for c in self.estimator.config.cameras
            }
            relative = self.estimator.estimate(images, state)
            count = len(self.estimator.config.objects)
        else:
            env = np.asarray(observation["observation.environment_state"], np.float32)[None]
            relative = self.relative_poses(torch.from_numpy(state), torch.from_numpy(env))
            count = len(self.config.object_indices)
        return relative[0, : 3 * count].cpu().numpy().reshape(count, 3) / 10.0

    def reset(self) -> None:
        """Forget the predictions made so far and the gripper's state (call at each
        episode start)."""
        self.acting.reset()

    @property
    def needs_images(self) -> bool:
        return self.config.kind == "vla"

    def replay_views(self) -> dict[str, Any]:
        """What a replay buffer keeps for this policy (:class:`~twinrl_learn.replay.
        ReplayBuffer`'s ``cameras`` and ``estimate``): the cameras an image policy reads,
        and for one acting through a pose estimator its estimates, computed once per
        episode so that an RL update runs no image network."""
        return {
            "cameras": tuple(self.config.cameras) if self.needs_images else (),
            "estimate": self.estimator.estimate_rows if self.perceives else None,
        }

    # ------------------------------------------------------------ checkpoints
    def save_pretrained(self, path: str | Path) -> Path:
        """Write the checkpoint folder ``path`` (see :mod:`twinrl_learn.policy.checkpoint`)."""
        self.config.instructions = self.instructions.to_dict()
        return save_checkpoint(path, self.config, self.state_dict())

    @classmethod
    def from_pretrained(cls, path: str | Path, device: str | torch.device = "cpu") -> Policy:
        """The checkpoint in ``path``, on ``device`` (a name such as auto, or a device;
        wherever it was trained)."""
        config, weights = load_checkpoint(path)
        policy = cls(config)
        policy.load_state_dict(weights)
        policy.eval()
        return policy.to(resolve_device(device))
