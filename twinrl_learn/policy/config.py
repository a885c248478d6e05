"""The policy's configuration: architecture, inputs, acting and normalisation stats,
everything a checkpoint needs to rebuild it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from twinrl_learn.errors import LearnError
from twinrl_learn.settings import check_inputs

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
    # Acting, command the gripper open or closed, as the demonstrations do: an averaged
    # or regressed value between the two half-closes a position-servoed gripper on the
    # way down, and the fingers closed on the object's top (docs/results/defaults.md).
    binary_gripper: bool = True
    # Acting, hold a close until the tool is as low above the object under it as the
    # demonstrations close (close_height.CloseHeightRule), at ``close_height`` (m, read
    # from the demonstrations by SFT; None: the policy perceives no objects, or no
    # demonstrated close had one under the tool).
    close_as_demonstrated: bool = True
    close_height: float | None = None
    # The pose estimator an image policy acts through (EstimatorConfig as a dict; its
    # head's weights are in the checkpoint under ``estimator.``): it reads the cameras
    # and proprio and says where the objects are relative to the tool, and the policy
    # acts on that as the state policy does on the true poses (twinrl_learn.perception).
    # None: the cameras' own FiLM encoders, trained with the policy.
    estimator: dict | None = None
    seed: int = 0
    stats: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    instructions: dict[str, list[float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise LearnError(f"policy kind must be one of {', '.join(KINDS)}, got '{self.kind}'")
        if self.kind == "state" and self.env_dim == 0:
            raise LearnError("the state policy needs observation.environment_state (env_dim > 0)")
        check_inputs(self.inputs, self.kind)
        if self.stem_stride not in CONV_KERNELS:
            raise LearnError(
                f"stem_stride must be one of {sorted(CONV_KERNELS)}, got {self.stem_stride}"
            )
        if self.locate_weight < 0:
            raise LearnError(f"locate_weight must be >= 0, got {self.locate_weight}")
        if self.temporal_ensemble is not None and not 0 <= self.temporal_ensemble < math.inf:
            raise LearnError(
                f"temporal_ensemble must be a finite number >= 0 (or None: chunks open-loop), "
                f"got {self.temporal_ensemble}"
            )
        if self.estimator is not None and (self.kind != "vla" or self.locate_weight > 0):
            raise LearnError(
                "a pose estimator serves the vla policy, which then needs no locating head "
                "(locate_weight 0)"
            )
        if self.locate_weight > 0 and self.kind != "vla":
            raise LearnError(
                "locate_weight applies to the vla policy (the state policy reads poses)"
            )
        for needs, use in (
            (self.locate_weight > 0, "locating the objects needs"),
            (self.inputs == "relative", "relative inputs need"),
        ):
            if needs and (self.tcp_index < 0 or not self.object_indices):
                raise LearnError(
                    f"{use} a dataset whose state has the TCP pose (tcp.x ...) and whose "
                    "environment state has object poses (<name>.x ...)"
                )
