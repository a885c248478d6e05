"""The policy: camera images + language instruction + proprio -> an action (chunk).

Two variants share one head and one checkpoint format:

- ``vla``: a small CNN per camera (``front``, ``wrist``) trained from scratch, its
  feature maps FiLM-conditioned on the instruction's sentence embedding
  (all-MiniLM-L6-v2), fused with the proprio state. Where the training data hold the
  object poses (the twin's demos always do), an auxiliary head learns to say where each
  object is relative to the TCP from the same features (``locate_weight``): from 30-120
  demonstrations at 64 px a locating head placed the banana 1.2-1.8 cm off while the
  gripper approached it, which is a missed grasp;
- ``state`` (**privileged**): proprio + ``observation.environment_state`` (object poses
  known only in the twin and the plant), for fast experiments. Its ``inputs`` are either
  ``absolute`` (joint angles, TCP pose, gripper, the objects' poses in the base frame and
  their offsets from the TCP) or ``relative`` (TCP pose and gripper, and each object's
  offset from the TCP and orientation relative to the tool, nothing absolute about the
  objects): the same reach looks the same anywhere on the table, which makes a policy
  learnt from few demonstrations generalise more evenly.

The head is a tanh-squashed Gaussian over normalised actions in [-1, 1]: its
log-likelihood is the imitation loss now and the same network serves as the actor of
the Q-guided objective later. Actions are normalised with the dataset's min/max, states
with its mean/std.

Acting (:meth:`Policy.act`) with ``chunk > 1`` predicts a chunk at every step and
executes the average of all predictions for that step (temporal ensembling, as ACT
does), each weighted ``exp(-temporal_ensemble * i)`` with ``i = 0`` the oldest: a
chunk run open-loop for ``chunk`` steps cannot correct itself, and the grasps it missed
were off by a couple of centimetres or tens of degrees. ``temporal_ensemble = None``
executes each chunk open-loop, as RL's exploring rollouts do (their critic scores the
chunk it executes).

With ``grasp_hold`` the arm waits for the gripper (``HoldRule``), as a blocking
grasp call does on a real gripper: the demonstrations dwell while the fingers close,
but a policy's lift comes on its own clock, and the grasps it lost were lifted while
the fingers were still 3-6 cm apart.

A checkpoint is a folder::

    CKPT/
      config.json          PolicyConfig, normalisation stats, instruction embeddings
      model.safetensors    weights
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

from twinrl_learn.language import EMBEDDING_DIM, InstructionCache
from twinrl_learn.settings import check_inputs
from twinrl_robot.wrappers import HoldRule

KINDS = ("vla", "state")
LOG_STD_RANGE = (-5.0, 1.0)
ACTION_MARGIN = 0.9
EPS = 1e-4
IMAGE_SHIFT = 4  # pixels of random shift (pad + crop) augmentation
CONV_KERNELS = {2: (3, 1), 4: (8, 2)}  # convolution stride -> (kernel, padding)
STATE_NOISE = 0.1  # std of Gaussian noise on normalised state inputs during training


@dataclass
class PolicyConfig:
    """Architecture and normalisation; everything needed to rebuild the policy."""

    kind: str
    state_dim: int
    env_dim: int = 0
    action_dim: int = 7
    chunk: int = 1
    cameras: list[str] = field(default_factory=lambda: ["front", "wrist"])
    image_size: int = 64
    # Stride of each encoder's first convolution: 2 (3x3) for 64 px images, 4 (8x8) for
    # 128 px, which reaches the same 32x32 maps from 4x the pixels in about the same
    # training time (settings.STEM_STRIDES).
    stem_stride: int = 2
    # Weight of the auxiliary loss that locates the objects relative to the TCP (vla;
    # 0: no locating head). Trained where the data hold observation.environment_state.
    locate_weight: float = 0.0
    hidden: int = 256
    tcp_index: int = -1  # where tcp.x is in observation.state (-1: unknown)
    # Entries of observation.state the policy reads (default: all; SFT chooses them).
    state_inputs: list[int] = field(default_factory=list)
    object_indices: list[int] = field(default_factory=list)  # where each <object>.x is in env
    inputs: str = "absolute"  # the state policy's view of the objects (see the module doc)
    # Acting, the i-th oldest prediction for a step weighs exp(-temporal_ensemble * i)
    # (module doc; ACT's 0.01: older ones weigh slightly more); None: chunks open-loop.
    # Ensembling measured better than open-loop chunks (docs/results/defaults.md).
    temporal_ensemble: float | None = 0.01
    # Acting, hold the arm while the gripper closes (HoldRule).
    # State policies gained successes with it, none lost any (docs/results/defaults.md).
    grasp_hold: bool = True
    seed: int = 0
    stats: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    instructions: dict[str, list[float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"policy kind must be one of {', '.join(KINDS)}, got '{self.kind}'")
        if self.kind == "state" and self.env_dim == 0:
            raise ValueError("the state policy needs observation.environment_state (env_dim > 0)")
        check_inputs(self.inputs, self.kind)
        if self.stem_stride not in CONV_KERNELS:
            raise ValueError(
                f"stem_stride must be one of {sorted(CONV_KERNELS)}, got {self.stem_stride}"
            )
        if self.locate_weight < 0:
            raise ValueError(f"locate_weight must be >= 0, got {self.locate_weight}")
        if self.temporal_ensemble is not None and not 0 <= self.temporal_ensemble < math.inf:
            raise ValueError(
                f"temporal_ensemble must be a finite number >= 0 (or None: chunks open-loop), "
                f"got {self.temporal_ensemble}"
            )
        if self.locate_weight > 0 and self.kind != "vla":
            raise ValueError(
                "locate_weight applies to the vla policy (the state policy reads poses)"
            )
        for needs, use in (
            (self.locate_weight > 0, "locating the objects needs"),
            (self.inputs == "relative", "relative inputs need"),
        ):
            if needs and (self.tcp_index < 0 or not self.object_indices):
                raise ValueError(
                    f"{use} a dataset whose state has the TCP pose (tcp.x ...) and whose "
                    "environment state has object poses (<name>.x ...)"
                )


class SpatialSoftmax(nn.Module):
    """Expected image coordinates of each channel's softmax: where things are."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c, h, w = x.shape
        weights = torch.softmax(x.flatten(2), dim=-1).view(n, c, h, w)
        ys = torch.linspace(-1, 1, h, device=x.device)
        xs = torch.linspace(-1, 1, w, device=x.device)
        return torch.cat([(weights.sum(3) * ys).sum(-1), (weights.sum(2) * xs).sum(-1)], dim=-1)


class FiLMConvEncoder(nn.Module):
    """Four conv blocks; each block's channels are scaled and shifted by the instruction
    embedding (FiLM); a spatial softmax turns the last maps into keypoints. The first
    block strides by ``stem_stride`` (:data:`CONV_KERNELS`), the others by 2."""

    def __init__(self, channels: tuple[int, ...] = (32, 64, 64, 128), stem_stride: int = 2) -> None:
        super().__init__()
        blocks, films = [], []
        previous = 3
        for i, width in enumerate(channels):
            stride = stem_stride if i == 0 else 2
            kernel, padding = CONV_KERNELS[stride]
            blocks.append(
                nn.Sequential(
                    nn.Conv2d(previous, width, kernel, stride=stride, padding=padding),
                    nn.GroupNorm(8, width),
                )
            )
            films.append(nn.Linear(EMBEDDING_DIM, 2 * width))
            previous = width
        self.blocks = nn.ModuleList(blocks)
        self.films = nn.ModuleList(films)
        self.keypoints = SpatialSoftmax()
        self.out_dim = 2 * previous

    def forward(self, images: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        x = images
        for block, film in zip(self.blocks, self.films, strict=True):
            gamma, beta = film(text).chunk(2, dim=-1)
            x = block(x) * (1 + gamma[..., None, None]) + beta[..., None, None]
            x = F.relu(x)
        return self.keypoints(x)


class Policy(nn.Module):
    """See the module docstring. ``forward`` works on normalised tensors; :meth:`act`
    takes one observation dict of the episode contract and returns a physical action."""

    def __init__(self, config: PolicyConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.encoders = nn.ModuleDict()
        features = 0
        if c.kind == "vla":
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
        self._predictions: list[np.ndarray] = []  # the unexecuted rest of each chunk
        self._grasp_hold = HoldRule()
        self._stats = {k: {s: torch.tensor(v) for s, v in d.items()} for k, d in c.stats.items()}

    @property
    def locates(self) -> bool:
        """Whether the image policy has the auxiliary head that locates the objects."""
        return self.config.kind == "vla" and self.config.locate_weight > 0

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
        """What the state policy reads of a normalised batch."""
        if self.config.inputs == "relative":
            return [batch["state"], batch["relative"]]
        return [batch["state"], batch["env"], batch["relative"]]

    # ------------------------------------------------------------------ core
    def keypoints(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """The image encoders' keypoints of a normalised batch, every camera's in turn
        (None for the state policy). They are most of an image policy's cost, so an RL
        update computes them once per batch and hands them to :meth:`features` and
        :meth:`critic_inputs`."""
        if self.config.kind != "vla":
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
        if self.config.kind == "vla":
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
        if self.config.kind == "vla":
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
        if c.kind == "vla":
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
        out = self.head(features).view(-1, self.config.chunk, 2, self.config.action_dim)
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
            located = self.locator(features[known])
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
            "objects": self.relative_poses(state, torch.nan_to_num(env)),
            "objects_known": known,
        }

    def locate(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Where the image policy sees each object relative to the TCP: (B, 3 x objects)
        in decimetres along the base axes, the scale of :meth:`relative_poses`."""
        if not self.locates:
            raise ValueError("this policy has no locating head (trained with locate_weight 0)")
        return self.locator(self.features(batch))

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
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
        return torch.tanh(mean + std_scale * log_std.exp() * noise)

    # ------------------------------------------------------------ normalising
    def _action_range(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Dataset min/max per action dimension; a constant dimension maps to itself."""
        low, high = self._stats["action"]["min"], self._stats["action"]["max"]
        constant = (high - low) < 1e-6
        return torch.where(constant, low - 1, low), torch.where(constant, high + 1, high)

    def normalize(self, key: str, values: torch.Tensor) -> torch.Tensor:
        """States to zero mean and unit std; actions from [min, max] to [-0.9, 0.9], so
        that demonstrated extremes stay where the tanh is not yet flat."""
        stats = self._stats[key]
        if key == "action":
            low, high = self._action_range()
            return ACTION_MARGIN * (2 * (values - low) / (high - low) - 1)
        normalized = (values - stats["mean"]) / stats["std"].clamp_min(1e-6)
        if key == "state" and self.config.state_inputs:
            normalized = normalized[..., self.config.state_inputs]
        return normalized

    def unnormalize_action(self, values: torch.Tensor) -> torch.Tensor:
        """Back to physical units, within the demonstrated range; a dimension that never
        varied in the data (e.g. tilting a top-down tool) keeps its constant value."""
        low, high = self._action_range()
        physical = (values / ACTION_MARGIN + 1) / 2 * (high - low) + low
        data_low, data_high = self._stats["action"]["min"], self._stats["action"]["max"]
        return torch.minimum(torch.maximum(physical, data_low), data_high)

    def relative_poses(self, state: torch.Tensor, env: torch.Tensor) -> torch.Tensor:
        """Each object's position relative to the TCP (m x 10, base axes): what a reaching
        policy needs, invariant to where on the table things are. With ``relative`` inputs
        also its orientation in the tool frame (the first two columns of R_tool^T R_object,
        a continuous rotation code): how far the tool must still turn to grasp it."""
        if not self.config.object_indices:
            return state.new_zeros((state.shape[0], 0))
        start = self.config.tcp_index
        tcp = state[:, start : start + 3]
        parts = [(env[:, i : i + 3] - tcp) * 10.0 for i in self.config.object_indices]
        if self.config.inputs == "relative":
            tool = quat_matrix(state[:, start + 3 : start + 7])
            for i in self.config.object_indices:
                rotation = tool.transpose(1, 2) @ quat_matrix(env[:, i + 3 : i + 7])
                parts.append(rotation[:, :, :2].reshape(len(rotation), 6))
        return torch.cat(parts, dim=-1)

    def prepare_images(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 (B, H, W, 3) -> float (B, 3, S, S) in [0, 1] at the policy's image size."""
        x = images.permute(0, 3, 1, 2).float() / 255.0
        size = self.config.image_size
        if x.shape[-1] != size or x.shape[-2] != size:
            x = F.interpolate(
                x, size=(size, size), mode="bilinear", align_corners=False, antialias=True
            )
        return x

    def inputs(
        self,
        state: np.ndarray | torch.Tensor,
        environment_state: np.ndarray | torch.Tensor | None,
        images: dict[str, np.ndarray | torch.Tensor],
        instructions: list[str],
    ) -> dict[str, torch.Tensor]:
        """A normalised input batch from raw arrays (B rows): what :meth:`features` reads."""
        state = torch.as_tensor(np.asarray(state, np.float32))
        batch = {
            "state": self.normalize("state", state),
            "text": torch.as_tensor(np.stack([self.instructions(i) for i in instructions])),
        }
        if self.config.kind == "vla":
            for camera in self.config.cameras:
                batch[f"image.{camera}"] = self.prepare_images(torch.as_tensor(images[camera]))
        else:
            if environment_state is None:
                raise ValueError("the state policy needs observation.environment_state")
            env = torch.as_tensor(np.asarray(environment_state, np.float32))
            batch["env"] = self.normalize("env", env)
            batch["relative"] = self.relative_poses(state, env)
        return batch

    def augment(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator
    ) -> dict[str, torch.Tensor]:
        """A training copy of a normalised batch: images shifted by up to IMAGE_SHIFT
        pixels, states with STATE_NOISE std units of noise (robustness to the small
        state errors a rollout makes). SFT and the RL actor's imitation term both use
        it, so fine-tuning keeps the input tolerance the policy was trained with."""
        out = dict(batch)
        if self.config.kind == "vla":
            for camera in self.config.cameras:
                out[f"image.{camera}"] = _random_shift(out[f"image.{camera}"], generator)
        for key in ("state", "env", "relative"):
            if key in out:
                noise = torch.randn(out[key].shape, generator=generator) * STATE_NOISE
                out[key] = out[key] + noise
        return out

    def observation_inputs(
        self, observations: dict[str, Any], instructions: list[str]
    ) -> dict[str, torch.Tensor]:
        """:meth:`inputs` from a batch of contract observations (leading batch axis)."""
        images = {}
        if self.config.kind == "vla":
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
        return self.unnormalize_action(actions).numpy().astype(np.float32)

    def act(
        self, observation: dict[str, Any], instruction: str, deterministic: bool = True
    ) -> np.ndarray:
        """The next action (physical units) for one observation of the episode contract.

        With ``chunk > 1`` and ``temporal_ensemble`` set, it predicts a chunk at every
        step and returns the weighted average of every prediction made for this step;
        without ``temporal_ensemble`` it executes each chunk in turn before looking again.
        With ``grasp_hold`` the arm holds while the gripper closes (``HoldRule``).
        :meth:`reset` starts afresh.
        """
        action = self._next_action(observation, instruction, deterministic)
        if self.config.grasp_hold:
            action = self._grasp_hold(np.asarray(observation["observation.state"]), action)
        return action

    def _next_action(
        self, observation: dict[str, Any], instruction: str, deterministic: bool
    ) -> np.ndarray:
        coefficient = self.config.temporal_ensemble
        # Each earlier prediction moves on by the step executed since.
        self._predictions = [rest[1:] for rest in self._predictions if len(rest) > 1]
        if coefficient is None and self._predictions:
            return self._predictions[0][0]
        batch = {k: np.asarray(v)[None] for k, v in observation.items()}
        chunk = self.act_chunks(batch, [instruction], deterministic)[0]
        self._predictions.append(chunk)
        if coefficient is None:
            return chunk[0]
        for_now = np.stack([rest[0] for rest in self._predictions])  # oldest first
        weights = np.exp(-coefficient * np.arange(len(for_now)))
        return (weights @ for_now / weights.sum()).astype(np.float32)

    def reset(self) -> None:
        """Forget the predictions made so far and the gripper's state (call at each
        episode start)."""
        self._predictions = []
        self._grasp_hold = HoldRule()

    @property
    def needs_images(self) -> bool:
        return self.config.kind == "vla"

    # ------------------------------------------------------------ checkpoints
    def save_pretrained(self, path: str | Path) -> Path:
        """Write ``config.json`` and ``model.safetensors`` into the folder ``path``."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        self.config.instructions = self.instructions.to_dict()
        (path / "config.json").write_text(json.dumps(asdict(self.config), indent=1))
        weights = {k: v.contiguous() for k, v in self.state_dict().items()}
        save_file(weights, path / "model.safetensors")
        return path

    @classmethod
    def from_pretrained(cls, path: str | Path) -> Policy:
        path = Path(path)
        if not (path / "config.json").is_file() or not (path / "model.safetensors").is_file():
            raise ValueError(
                f"{path} is not a twinrl policy checkpoint "
                "(needs config.json and model.safetensors)"
            )
        config = PolicyConfig(**json.loads((path / "config.json").read_text()))
        policy = cls(config)
        policy.load_state_dict(load_file(path / "model.safetensors"))
        policy.eval()
        return policy


def is_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` is a twinrl policy checkpoint (lerobot's have a ``type`` instead)."""
    path = Path(path)
    if not ((path / "config.json").is_file() and (path / "model.safetensors").is_file()):
        return False
    try:
        return json.loads((path / "config.json").read_text()).get("kind") in KINDS
    except json.JSONDecodeError:
        return False


def _random_shift(images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Pad by IMAGE_SHIFT (replicate) and crop back at a random offset per image."""
    n, _, h, w = images.shape
    padded = F.pad(images, (IMAGE_SHIFT,) * 4, mode="replicate")
    offsets = torch.randint(0, 2 * IMAGE_SHIFT + 1, (n, 2), generator=generator).tolist()
    return torch.stack(
        [padded[i, :, dy : dy + h, dx : dx + w] for i, (dy, dx) in enumerate(offsets)]
    )


def quat_matrix(quat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in (w, x, y, z) order."""
    w, x, y, z = (quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-9)).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).view(*quat.shape[:-1], 3, 3)
