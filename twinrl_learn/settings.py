"""The settings records of SFT and RL, with their defaults and checks.

They live apart from the networks (``sft``, ``agent``, ``policy``) so that the command
line can show their defaults, and refuse bad values, without loading torch.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

from twinrl_learn.errors import LearnError
from twinrl_learn.replay import RewardSettings

INPUTS = ("absolute", "relative")


def check_inputs(inputs: str, kind: str) -> None:
    """Refuse ``inputs`` that are unknown or that the policy ``kind`` cannot have: the
    one check behind SFT, its CLI and the pipeline, made before any work starts."""
    if inputs not in INPUTS:
        raise LearnError(f"--inputs must be one of {', '.join(INPUTS)}, got '{inputs}'")
    if inputs != "absolute" and kind != "state":
        raise LearnError(
            f"--inputs applies to --policy state only: {inputs} inputs need the state policy "
            "(the vla policy sees images)"
        )


class Defaults(NamedTuple):
    """The SFT settings of a policy kind that no option overrides."""

    steps: int
    batch_size: int
    lr: float
    lr_schedule: str  # one of LR_SCHEDULES


# Enough for 30-120 episodes in a few minutes on 2 cores. The state policy's final
# weights were a noisy iterate at a constant rate; the image policy's were better at one
# (docs/results/sft.md has the figures).
DEFAULTS = {
    "state": Defaults(steps=3000, batch_size=256, lr=1e-3, lr_schedule="cosine"),
    "vla": Defaults(steps=5000, batch_size=64, lr=5e-4, lr_schedule="constant"),
}
# The image policy's input sizes (the cameras record 128 px) and the stride of its
# encoders' first convolution for each: both reach 32x32 feature maps.
STEM_STRIDES = {64: 2, 128: 4}
IMAGE_SIZES = tuple(STEM_STRIDES)
# How the learning rate runs over the steps (see learning_rate).
LR_SCHEDULES = ("cosine", "constant")


@dataclass
class SFTConfig:
    """What to train on and how. ``None`` fields take the defaults of the policy kind, or
    in a resumed run the run's own settings."""

    datasets: list[str]
    out: str
    policy: str = "vla"
    weights: list[float] | None = None
    steps: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    lr_schedule: str | None = None  # cosine (decay to zero) or constant; None: by policy
    chunk: int = 8
    inputs: str = "absolute"  # the state policy's inputs: absolute or relative (policy.py)
    image_size: int = 128  # vla: images are resized to this on load (64 or 128)
    # vla: weight of the auxiliary object-locating loss (0: off). Its squared error is in
    # decimetres (a 1 cm miss costs 0.01); 10 beat 1 and 30 (docs/results/defaults.md).
    locate_weight: float = 10.0
    seed: int = 0
    checkpoint_every: int = 500
    log_every: int = 25

    def __post_init__(self) -> None:
        check_inputs(self.inputs, self.policy)
        if self.image_size not in IMAGE_SIZES:
            raise LearnError(
                f"--image-size must be one of {', '.join(map(str, IMAGE_SIZES))}, "
                f"got {self.image_size}"
            )
        if self.locate_weight < 0:
            raise LearnError(f"--locate-weight must be >= 0, got {self.locate_weight}")
        if self.lr_schedule not in (None, *LR_SCHEDULES):
            raise LearnError(
                f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, got '{self.lr_schedule}'"
            )

    def resolved(self) -> SFTConfig:
        defaults = DEFAULTS[self.policy]
        return SFTConfig(
            **{
                **asdict(self),
                "steps": self.steps or defaults.steps,
                "batch_size": self.batch_size or defaults.batch_size,
                "lr": self.lr or defaults.lr,
                "lr_schedule": self.lr_schedule or defaults.lr_schedule,
            }
        )


METHODS = ("twinrl", "conrft", "hil-serl")


@dataclass
class RLConfig:
    """Hyper-parameters of the agent (defaults: TwinRL's where the paper gives them)."""

    method: str = "twinrl"
    gamma: float = 0.98
    tau: float = 0.005
    critics: int = 2
    hidden: int = 256
    batch_size: int = 64  # as in the paper
    # Small: 3e-4 wore the fine-tuned SFT policy down in real RL (docs/results/defaults.md).
    # SAC without an imitation term keeps 3e-4.
    actor_lr: float = 3e-5
    critic_lr: float = 3e-4
    beta: float = 1.0  # weight of L_IL
    # Weight of L_Q; at 1 the young critic undid the SFT policy (docs/results/defaults.md).
    eta: float = 0.1
    beta_online: float | None = None  # beta after the offline phase (None: unchanged)
    cql_alpha: float = 0.1
    cql_actions: int = 4
    entropy: bool = False  # SAC temperature term in the actor and the TD target
    target_entropy_per_dim: float = -1.0
    demo_ratio: float = 0.5  # share of each batch from demos + interventions (RLPD)
    # Rollouts sample with the policy's spread times this: a spread learned by BC from
    # noisy teleop is too wide for mm-precise tasks (SAC learns its own: 1.0).
    exploration: float = 0.3
    utd: float = 1.0  # gradient updates per environment step
    offline_steps: int = 500
    rewards: RewardSettings = field(default_factory=RewardSettings)
    seed: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.rewards, dict):
            self.rewards = RewardSettings(**self.rewards)
        if self.method not in METHODS:
            raise LearnError(f"method must be one of {', '.join(METHODS)}, got '{self.method}'")
        if self.critics < 2:
            raise LearnError(f"the critic ensemble needs at least 2 members, got {self.critics}")
        if not 0 <= self.demo_ratio <= 1:
            raise LearnError(f"demo_ratio must be in [0, 1], got {self.demo_ratio}")
        if self.beta < 0 or self.eta < 0:
            raise LearnError("beta and eta must be non-negative")

    @classmethod
    def load(cls, folder: str | Path) -> RLConfig:
        """The settings an RL checkpoint folder was trained with."""
        path = Path(folder) / "rl_config.json"
        if not path.is_file():
            raise LearnError(f"{folder} holds no rl_config.json; it is not an RL checkpoint")
        return cls(**json.loads(path.read_text()))

    @classmethod
    def for_method(cls, method: str, **overrides) -> RLConfig:
        """The settings that define each compared method."""
        base: dict = {"method": method}
        if method == "hil-serl":
            base |= {
                "beta": 0.0,
                "eta": 1.0,
                "entropy": True,
                "offline_steps": 0,
                "cql_alpha": 0.0,
                "exploration": 1.0,
                "actor_lr": 3e-4,
            }
        return cls(**(base | overrides))
