"""The image policy's encoder: FiLM-conditioned convolutions and spatial-softmax
keypoints."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from twinrl_learn.language import EMBEDDING_DIM
from twinrl_learn.policy.config import CONV_KERNELS


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
