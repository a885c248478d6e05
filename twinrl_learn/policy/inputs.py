"""What the policy reads of an observation: normalised states, the objects relative to
the tool, resized images and the instruction's embedding, as one batch of tensors."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from twinrl_learn.errors import LearnError
from twinrl_learn.language import InstructionCache
from twinrl_learn.policy.config import PolicyConfig
from twinrl_learn.policy.normalization import Normalizer

if TYPE_CHECKING:
    from twinrl_learn.perception.estimator import PoseEstimator


class InputEncoder:
    """Turns raw arrays (or contract observations) into the normalised batch the
    networks read."""

    def __init__(
        self,
        config: PolicyConfig,
        normalizer: Normalizer,
        instructions: InstructionCache,
        estimator: PoseEstimator | None = None,
    ) -> None:
        self.config, self.normalizer, self.instructions = config, normalizer, instructions
        self.estimator = estimator

    def relative_poses(self, state: torch.Tensor, env: torch.Tensor) -> torch.Tensor:
        """See :func:`relative_poses`; orientations with ``relative`` inputs."""
        config = self.config
        return relative_poses(
            state, env, config.tcp_index, config.object_indices, config.inputs == "relative"
        )

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
        estimates: np.ndarray | torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """A normalised input batch from raw arrays (B rows). A policy that acts through a
        pose estimator reads its ``estimates`` of these rows when given (SFT computes them
        once per frame), or runs it on ``images``."""
        state = torch.as_tensor(np.asarray(state, np.float32))
        batch = {
            "state": self.normalizer.normalize("state", state),
            "text": torch.as_tensor(np.stack([self.instructions(i) for i in instructions])),
        }
        if self.estimator is not None:
            if estimates is None:
                estimates = self.estimator.estimate(images, state)
            batch["relative"] = torch.as_tensor(np.asarray(estimates, np.float32))
        elif self.config.kind == "vla":
            for camera in self.config.cameras:
                batch[f"image.{camera}"] = self.prepare_images(torch.as_tensor(images[camera]))
        else:
            if environment_state is None:
                raise LearnError("the state policy needs observation.environment_state")
            env = torch.as_tensor(np.asarray(environment_state, np.float32))
            batch["env"] = self.normalizer.normalize("env", env)
            batch["relative"] = self.relative_poses(state, env)
        return batch


def relative_poses(
    state: torch.Tensor,
    env: torch.Tensor,
    tcp_index: int,
    object_indices: list[int],
    orientations: bool,
) -> torch.Tensor:
    """Each object's position relative to the TCP (m x 10, base axes): what a reaching
    policy needs, invariant to where on the table things are. With ``orientations`` also
    its orientation in the tool frame (the first two columns of R_tool^T R_object, a
    continuous rotation code): how far the tool must still turn to grasp it. ``state``
    holds the TCP pose from ``tcp_index`` (xyz, quaternion wxyz), ``env`` each object's
    from its index in ``object_indices``."""
    if not object_indices:
        return state.new_zeros((state.shape[0], 0))
    tcp = state[:, tcp_index : tcp_index + 3]
    parts = [(env[:, i : i + 3] - tcp) * 10.0 for i in object_indices]
    if orientations:
        tool = quat_matrix(state[:, tcp_index + 3 : tcp_index + 7])
        for i in object_indices:
            rotation = tool.transpose(1, 2) @ quat_matrix(env[:, i + 3 : i + 7])
            parts.append(rotation[:, :, :2].reshape(len(rotation), 6))
    return torch.cat(parts, dim=-1)


def quat_matrix(quat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in (w, x, y, z) order."""
    w, x, y, z = (quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-9)).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).view(*quat.shape[:-1], 3, 3)
