"""The object pose estimator: where each object is relative to the tool, from the cameras.

It reads what a real cell has (the ``front`` and ``wrist`` images and the arm's own TCP
pose and gripper) and says, per object, its offset from the TCP (decimetres, base axes)
and its orientation in the tool frame (the 6-number rotation code), the same
:func:`~twinrl_learn.policy.inputs.relative_poses` the state policy reads from the
privileged object poses. Its labels are free in the twin, so it learns from thousands of
placements rendered there (:mod:`twinrl_learn.perception.training`), not from the
hundred a person demonstrates; an image policy then acts on its estimates.

Each camera's frozen ImageNet features (:mod:`~twinrl_learn.perception.backbone`) go
through a small trained head: 1x1 projections of both feature levels, summed at
stride 8, a 3x3 convolution, and a spatial softmax whose expected coordinates say
where things are, beside the maps' mean (what is there). An MLP joins both cameras and
the proprio.

A checkpoint is a folder::

    EST/config.json          EstimatorConfig
    EST/model.safetensors    the trained head (the backbone comes from its package)
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save
from torch import nn

from twinrl_data.atomic import write_atomic
from twinrl_learn.compute import mixed_precision, module_device, resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.perception.backbone import CHANNELS, FrozenBackbone
from twinrl_learn.policy.networks import SpatialSoftmax

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"


@dataclass
class EstimatorConfig:
    """Everything needed to rebuild an estimator and feed it an observation."""

    cameras: list[str]
    objects: list[str]  # object names, in the order of the outputs
    proprio_names: list[str]  # the observation.state entries it reads (TCP pose, gripper)
    state_names: list[str]  # observation.state's names where it was trained
    proprio_mean: list[float]
    proprio_std: list[float]
    image_size: int = 128
    keypoints: int = 32
    hidden: int = 256
    head_width: int = 64  # channels of each camera's head (estimators before it had 64)
    seed: int = 0
    trained_on: list[str] = field(default_factory=list)  # the datasets it learnt from

    @property
    def output_dim(self) -> int:
        return 9 * len(self.objects)


class CameraHead(nn.Module):
    """Keypoints and a pooled summary of one camera's frozen feature maps."""

    def __init__(self, keypoints: int, width: int) -> None:
        super().__init__()
        fine, coarse = CHANNELS
        self.fine = nn.Conv2d(fine, width, 1)
        self.coarse = nn.Conv2d(coarse, width, 1)
        self.mix = nn.Sequential(
            nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=1),
            nn.GroupNorm(8, width),
            nn.ReLU(),
        )
        self.points = nn.Conv2d(width, keypoints, 1)
        self.softmax = SpatialSoftmax()
        self.out_dim = 2 * keypoints + width

    def forward(self, fine: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(self.coarse(coarse.float()), size=fine.shape[-2:], mode="nearest")
        x = self.mix(self.fine(fine.float()) + up)
        return torch.cat([self.softmax(self.points(x)), x.mean(dim=(2, 3))], dim=-1)


class PoseEstimator(nn.Module):
    """See the module docstring. :meth:`forward` reads cached backbone features;
    :meth:`estimate` reads raw observations."""

    def __init__(self, config: EstimatorConfig) -> None:
        super().__init__()
        self.config = config
        self.heads = nn.ModuleDict(
            {c: CameraHead(config.keypoints, config.head_width) for c in config.cameras}
        )
        width = sum(h.out_dim for h in self.heads.values()) + len(config.proprio_names)
        self.mlp = nn.Sequential(
            nn.Linear(width, config.hidden),
            nn.LayerNorm(config.hidden),
            nn.ReLU(),
            nn.Linear(config.hidden, config.hidden),
            nn.ReLU(),
            nn.Linear(config.hidden, config.output_dim),
        )
        self.register_buffer("proprio_mean", torch.tensor(config.proprio_mean))
        self.register_buffer("proprio_std", torch.tensor(config.proprio_std))
        self.proprio_columns = [config.state_names.index(n) for n in config.proprio_names]
        self._backbone: FrozenBackbone | None = None

    @property
    def backbone(self) -> FrozenBackbone:
        if self._backbone is None:
            self._backbone = FrozenBackbone()
        return self._backbone

    def proprio(self, state: torch.Tensor) -> torch.Tensor:
        """The normalised proprio entries of raw ``observation.state`` rows."""
        return (state[:, self.proprio_columns] - self.proprio_mean) / self.proprio_std

    def forward(
        self, features: dict[str, tuple[torch.Tensor, torch.Tensor]], state: torch.Tensor
    ) -> torch.Tensor:
        """Relative poses (B, 9 x objects) from each camera's (fine, coarse) features."""
        parts = [self.heads[c](*features[c]) for c in self.config.cameras]
        parts.append(self.proprio(state))
        return self.mlp(torch.cat(parts, dim=-1))

    def prepared(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 images (B, H, W, 3) as the backbone reads them: float (B, 3, S, S) in
        [0, 1] at the estimator's size."""
        x = images.permute(0, 3, 1, 2).float() / 255.0
        size = self.config.image_size
        if x.shape[-1] != size or x.shape[-2] != size:
            x = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True)
        return x

    def features(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Backbone features of uint8 images (B, H, W, 3) at the estimator's size."""
        return self.backbone(self.prepared(images))

    @torch.no_grad()
    def estimate(
        self, images: dict[str, np.ndarray | torch.Tensor], state: np.ndarray | torch.Tensor
    ) -> torch.Tensor:
        """Relative poses (B, 9 x objects, on the CPU) of raw rows: uint8 images per
        camera and raw ``observation.state``, run on the estimator's device."""
        missing = [c for c in self.config.cameras if c not in images]
        if missing:
            raise LearnError(
                f"the pose estimator needs the camera(s) {missing}; the observation has "
                f"{sorted(images)}"
            )
        device = module_device(self)
        state = torch.as_tensor(np.asarray(state, np.float32)).to(device)
        with mixed_precision(device):
            features = {
                c: self.features(torch.as_tensor(images[c]).to(device)) for c in self.config.cameras
            }
            return self(features, state).float().cpu()

    def estimate_rows(
        self, images: dict[str, np.ndarray], state: np.ndarray, batch: int = 128
    ) -> np.ndarray:
        """:meth:`estimate` of many rows (an episode, a dataset), a batch at a time."""
        parts = [
            self.estimate({c: images[c][i : i + batch] for c in self.config.cameras},
                          state[i : i + batch])
            for i in range(0, len(state), batch)
        ]  # fmt: skip
        if not parts:
            return np.zeros((0, self.config.output_dim), np.float32)
        return torch.cat(parts).numpy()

    def save_pretrained(self, path: str | Path) -> Path:
        """Write the checkpoint folder (the trained head and its config)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        weights = {k: v.contiguous() for k, v in self.state_dict().items()}
        write_atomic(path / WEIGHTS_FILE, save(weights))
        write_atomic(path / CONFIG_FILE, json.dumps(asdict(self.config), indent=1).encode())
        return path

    @classmethod
    def from_pretrained(cls, path: str | Path, device: str | torch.device = "cpu") -> PoseEstimator:
        """The estimator in ``path``, on ``device``."""
        path = Path(path)
        if not (path / CONFIG_FILE).is_file() or not (path / WEIGHTS_FILE).is_file():
            raise LearnError(
                f"{path} is not a pose estimator (needs {CONFIG_FILE} and {WEIGHTS_FILE}); "
                "train one with `twinrl train perception`"
            )
        config = EstimatorConfig(**json.loads((path / CONFIG_FILE).read_text()))
        estimator = cls(config)
        estimator.load_state_dict(load_file(path / WEIGHTS_FILE))
        estimator.eval()
        return estimator.to(resolve_device(device))


def rotation_from_code(code: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (B, 3, 3) of 6-number codes (B, 6): the matrices' first two
    columns, row by row, orthonormalised (Gram-Schmidt)."""
    a, b = code.reshape(-1, 3, 2).unbind(-1)
    x = F.normalize(a, dim=-1)
    y = F.normalize(b - (x * b).sum(-1, keepdim=True) * x, dim=-1)
    return torch.stack([x, y, torch.cross(x, y, dim=-1)], dim=-1)


def rotation_error_deg(predicted: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Angles (degrees) between rotations given as 6-number codes (two matrix columns;
    the predicted ones orthonormalised first), one per row of (B, 6)."""
    relative = rotation_from_code(predicted).transpose(1, 2) @ rotation_from_code(true)
    cosine = ((relative.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(cosine))
