"""Training-time augmentation: shifted images and noisy states, shared by SFT and the
RL actor's imitation term so that fine-tuning keeps the tolerance SFT trained."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from twinrl_learn.policy.config import IMAGE_SHIFT, STATE_NOISE, PolicyConfig


def augment(
    batch: dict[str, torch.Tensor], config: PolicyConfig, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """A training copy of a normalised batch: images shifted by up to IMAGE_SHIFT
    pixels, states with STATE_NOISE std units of noise (robustness to the small state
    errors a rollout makes). ``generator`` lives on the CPU wherever the batch is, so a
    seed draws the same augmentation on every device."""
    out = dict(batch)
    for camera in config.cameras:
        if f"image.{camera}" in out:
            out[f"image.{camera}"] = random_shift(out[f"image.{camera}"], generator)
    for key in ("state", "env", "relative"):
        if key in out:
            noise = torch.randn(out[key].shape, generator=generator) * STATE_NOISE
            out[key] = out[key] + noise.to(out[key].device)
    return out


def random_shift(images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Pad by IMAGE_SHIFT (replicate) and crop back at a random offset per image."""
    n, _, h, w = images.shape
    padded = F.pad(images, (IMAGE_SHIFT,) * 4, mode="replicate")
    offsets = torch.randint(0, 2 * IMAGE_SHIFT + 1, (n, 2), generator=generator).tolist()
    return torch.stack(
        [padded[i, :, dy : dy + h, dx : dx + w] for i, (dy, dx) in enumerate(offsets)]
    )
