"""Supervised fine-tuning (behaviour cloning) on one or more LeRobotDatasets.

Loss: the negative log-likelihood of the demonstrated (normalised) actions under the
policy's tanh-squashed Gaussian, i.e. TwinRL's L_IL = -E[log pi(a|s)] on D_human and
D_twin. Datasets are mixed by ``weights`` (per-dataset sampling probability; by default
in proportion to their frames, as if they were one dataset). The image
policy also learns to locate the objects relative to the TCP (``locate_weight`` times
the squared error of :meth:`Policy.locate`, on the frames that hold object poses).

Outputs, in the folder ``out``::

    out/config.json, out/model.safetensors     the final policy (Policy.from_pretrained)
    out/checkpoints/step_000500/...            periodic checkpoints
    out/training_state.pt                      optimizer, step, RNG and loss history
    out/loss.png                               the loss curve

``resume=True`` continues from ``training_state.pt`` exactly: the weights after N steps
are the same whether or not the run was interrupted.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from twinrl_data.training import FrameTable, load_frames
from twinrl_learn.policy import Policy, PolicyConfig, check_inputs

DEFAULTS = {
    # steps, batch size, learning rate and its schedule (LR_SCHEDULES): enough for 30-120
    # episodes in a few minutes on 2 cores
    "state": (3000, 256, 1e-3, "cosine"),
    "vla": (5000, 64, 5e-4, "constant"),
}
# The image policy's input sizes (the cameras record 128 px) and the stride of its
# encoders' first convolution for each: both reach 32x32 feature maps.
STEM_STRIDES = {64: 2, 128: 4}
IMAGE_SIZES = tuple(STEM_STRIDES)
# How the learning rate runs over the steps. With a constant rate the state policy's
# final weights are one noisy iterate: three SFT seeds on a quick run's demos ended at
# 58 / 86, 62 / 78 and 53 / 34 % (ID / OOD, 64 plant episodes per region each); decayed
# to zero along a cosine, at 70 / 81, 75 / 70 and 72 / 73 %. The image policy did not
# gain: on the fitted-look 30 / 60 mix the cosine gave 3 / 3 % against 19 / 16 %.
LR_SCHEDULES = ("cosine", "constant")
# What a run saved before an option existed had: it did not locate objects, and it kept
# its learning rate constant.
SAVED_BEFORE_OPTION = {"locate_weight": 0.0, "lr_schedule": "constant"}


@dataclass
class SFTConfig:
    """What to train on and how. ``None`` fields take the defaults of the policy kind."""

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
    locate_weight: float = 1.0  # vla: weight of the auxiliary object-locating loss (0: off)
    seed: int = 0
    checkpoint_every: int = 500
    log_every: int = 25

    def __post_init__(self) -> None:
        check_inputs(self.inputs, self.policy)
        if self.image_size not in IMAGE_SIZES:
            raise ValueError(
                f"--image-size must be one of {', '.join(map(str, IMAGE_SIZES))}, "
                f"got {self.image_size}"
            )
        if self.locate_weight < 0:
            raise ValueError(f"--locate-weight must be >= 0, got {self.locate_weight}")
        if self.lr_schedule not in (None, *LR_SCHEDULES):
            raise ValueError(
                f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, got '{self.lr_schedule}'"
            )

    def resolved(self) -> SFTConfig:
        steps, batch, lr, schedule = DEFAULTS[self.policy]
        return SFTConfig(
            **{
                **asdict(self),
                "steps": self.steps or steps,
                "batch_size": self.batch_size or batch,
                "lr": self.lr or lr,
                "lr_schedule": self.lr_schedule or schedule,
            }
        )


@dataclass
class SFTResult:
    out: Path
    steps: int
    losses: list[float] = field(default_factory=list)
    seconds: float = 0.0
    locating: bool = False  # whether the image policy learnt to locate the objects


def _frames(config: SFTConfig) -> FrameTable:
    cameras = ["front", "wrist"] if config.policy == "vla" else []
    return load_frames(config.datasets, cameras=cameras, image_size=config.image_size)


def _batch(
    policy: Policy,
    frames: FrameTable,
    rows: np.ndarray,
    generator: torch.Generator,
    chunk: int,
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """An augmented, normalised training batch of ``rows`` and their action chunks."""
    batch = policy.inputs(
        frames.state[rows],
        None if frames.environment_state is None else frames.environment_state[rows],
        {camera: frames.images[camera][rows] for camera in frames.images},
        [frames.instruction[r] for r in rows],
    )
    actions = policy.normalize("action", torch.from_numpy(frames.action_chunks(rows, chunk)))
    batch = policy.augment(batch, generator)
    if policy.locates:
        batch |= policy.locating_targets(frames.state[rows], frames.environment_state[rows])
    return batch, actions


def _sample_rows(
    frames: FrameTable, weights: np.ndarray, size: int, generator: torch.Generator
) -> np.ndarray:
    """Rows drawn by dataset weight, then uniformly within the dataset."""
    choice = torch.multinomial(
        torch.from_numpy(weights), size, replacement=True, generator=generator
    ).numpy()
    rows = np.empty(size, dtype=np.int64)
    for dataset in np.unique(choice):
        members = np.flatnonzero(frames.source == dataset)
        picks = torch.randint(
            0, len(members), (int((choice == dataset).sum()),), generator=generator
        ).numpy()
        rows[choice == dataset] = members[picks]
    return rows


def train_sft(
    config: SFTConfig,
    *,
    resume: bool = False,
    progress: Callable[[int, dict[str, float]], None] | None = None,
    frames: FrameTable | None = None,
) -> SFTResult:
    """Train (or continue training) a policy; ``progress(step, metrics)`` is called every
    ``log_every`` steps with ``loss``, ``steps_per_s`` and ``steps`` (the run's length).
    A resumed run without ``steps`` trains to the steps it was started with."""
    out = Path(config.out)
    state_file = out / "training_state.pt"
    if out.exists() and any(out.iterdir()) and not resume:
        raise ValueError(
            f"{out} already holds a run; pass --resume to continue it or choose another --out"
        )
    if resume and not state_file.is_file():
        raise ValueError(f"--resume: {state_file} does not exist (nothing to continue)")
    saved = torch.load(state_file, weights_only=False) if resume else None
    if saved is not None:
        _check_same_network(saved["config"], config.resolved(), out)
        before = saved["config"].get("lr_schedule", SAVED_BEFORE_OPTION["lr_schedule"])
        if config.lr_schedule not in (None, before):
            raise ValueError(
                f"--resume: {out} was trained with --lr-schedule {before}; resume it without "
                "--lr-schedule"
            )
        config = replace(config, steps=config.steps or saved["config"]["steps"], lr_schedule=before)
    config = config.resolved()
    frames = frames or _frames(config)
    weights = _resolve_weights(config, frames, saved)
    config = replace(config, weights=weights.tolist())
    # Joint velocities are a clock in demonstrations that a rollout does not keep; relative
    # inputs also leave out joint angles, which would tell the policy where it is.
    ignored_state = ("qd.", "q.") if config.inputs == "relative" else ("qd.",)
    tcp_index = frames.state_names.index("tcp.x") if "tcp.x" in frames.state_names else -1
    object_indices = (
        [i for i, n in enumerate(frames.environment_names) if n.endswith(".x")]
        if tcp_index >= 0
        else []
    )
    if config.policy == "state" and not frames.environment_complete:
        raise ValueError(
            "the state policy reads object poses (observation.environment_state), which "
            "some --dataset lacks; train --policy vla on it, or leave that dataset out"
        )
    # Locating learns from the frames that hold the objects' true poses (twin and plant
    # data do; a real cell's demos may not); with none, the image policy learns from the
    # actions alone.
    locating = (
        config.policy == "vla"
        and config.locate_weight > 0
        and frames.environment_state is not None
        and bool(object_indices)
    )
    torch.manual_seed(config.seed)
    policy_config = PolicyConfig(
        kind=config.policy,
        state_dim=frames.state.shape[1],
        env_dim=0 if frames.environment_state is None else frames.environment_state.shape[1],
        chunk=config.chunk,
        image_size=config.image_size,
        stem_stride=STEM_STRIDES[config.image_size],
        locate_weight=config.locate_weight if locating else 0.0,
        tcp_index=tcp_index,
        state_inputs=[
            i for i, n in enumerate(frames.state_names) if not n.startswith(ignored_state)
        ],
        object_indices=object_indices,
        inputs=config.inputs,
        seed=config.seed,
        stats={k: {s: v.tolist() for s, v in d.items()} for k, d in frames.stats.items()},
    )
    policy = Policy(policy_config)
    for instruction in sorted(set(frames.instruction)):
        policy.instructions(instruction)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=config.lr, weight_decay=1e-4)
    generator = torch.Generator().manual_seed(config.seed)
    step, losses = 0, []
    if saved is not None:
        policy.load_state_dict(saved["model"])
        optimizer.load_state_dict(saved["optimizer"])
        generator.set_state(saved["generator"])
        torch.set_rng_state(saved["torch_rng"])
        step, losses = saved["step"], saved["losses"]
    policy.train()
    start, window = time.perf_counter(), time.perf_counter()
    while step < config.steps:
        rows = _sample_rows(frames, weights, config.batch_size, generator)
        batch, actions = _batch(policy, frames, rows, generator, config.chunk)
        loss = policy.sft_loss(batch, actions)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(config, step)
        optimizer.step()
        step += 1
        losses.append(loss.item())
        if progress is not None and (step % config.log_every == 0 or step == config.steps):
            rate = config.log_every / max(time.perf_counter() - window, 1e-9)
            window = time.perf_counter()
            loss_now = float(np.mean(losses[-config.log_every :]))
            progress(step, {"loss": loss_now, "steps_per_s": rate, "steps": config.steps})
        if step % config.checkpoint_every == 0 or step == config.steps:
            _checkpoint(policy, optimizer, generator, step, losses, out, config)
    policy.eval()
    policy.save_pretrained(out)
    ylabel = "-log pi(a|s) + locating" if policy.locates else "-log pi(a|s)"
    plot_losses(losses, out / "loss.png", ylabel)
    return SFTResult(
        out=out,
        steps=step,
        losses=losses,
        seconds=time.perf_counter() - start,
        locating=policy.locates,
    )


def learning_rate(config: SFTConfig, step: int) -> float:
    """The learning rate of update ``step`` (from 0): along a cosine from ``lr`` to zero at
    the run's last step, or constant. A run resumed with more ``steps`` than it started
    with goes on along the cosine of its new length."""
    if config.lr_schedule == "constant":
        return config.lr
    return config.lr * 0.5 * (1 + math.cos(math.pi * step / config.steps))


def _resolve_weights(config: SFTConfig, frames: FrameTable, saved: dict | None) -> np.ndarray:
    """Each dataset's sampling probability: ``--weights`` normalised, or by default in
    proportion to its frames, as if the datasets were one. Mixing 30 noisy plant demos
    half and half with 210 twin demos held the state policy to 55 / 46 % (ID / OOD, mean
    of SFT seeds 0-2, 64 plant episodes per region each) against 58 / 66 % by frames. A
    resumed run keeps the weights it was trained with (equal, for runs saved before
    they were recorded) and refuses others."""
    count = len(config.datasets)
    if config.weights is not None and len(config.weights) != count:
        raise ValueError(f"--weights needs {count} values, one per --dataset")
    given = None if config.weights is None else np.asarray(config.weights, np.float64)
    if given is not None and ((given < 0).any() or given.sum() == 0):
        raise ValueError("--weights must be non-negative and not all zero")
    if saved is not None:
        before = np.asarray(saved["config"].get("weights") or [1.0] * count, np.float64)
        before = before / before.sum()
        if given is not None and not np.allclose(given / given.sum(), before):
            raise ValueError(
                f"--resume: {config.out} was trained with --weights "
                f"{','.join(f'{w:.4g}' for w in before)}; resume it without --weights"
            )
        return before
    if given is None:
        given = np.bincount(frames.source, minlength=count).astype(np.float64)
    return given / given.sum()


def _check_same_network(saved: dict, config: SFTConfig, out: Path) -> None:
    """A resumed run must build the network it saved (else its weights do not fit)."""
    image_only = ("image_size", "locate_weight") if config.policy == "vla" else ()
    differ = []
    for key in ("policy", "chunk", "inputs", *image_only):
        before = saved.get(
            key, SAVED_BEFORE_OPTION.get(key, SFTConfig.__dataclass_fields__[key].default)
        )
        if before != getattr(config, key):
            flag = "--" + key.replace("_", "-")
            differ.append((f"{flag} {before}", str(getattr(config, key))))
    if differ:
        raise ValueError(
            f"--resume: {out} was trained with {', '.join(d[0] for d in differ)}, not "
            f"{', '.join(d[1] for d in differ)}; resume it with the same options"
        )


def _checkpoint(policy, optimizer, generator, step, losses, out: Path, config: SFTConfig) -> None:
    policy.save_pretrained(out / "checkpoints" / f"step_{step:06d}")
    torch.save(
        {
            "model": policy.state_dict(),
            "optimizer": optimizer.state_dict(),
            "generator": generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "step": step,
            "losses": losses,
            "config": asdict(config),
        },
        out / "training_state.pt",
    )


def plot_losses(losses: list[float], path: Path, ylabel: str = "-log pi(a|s)") -> None:
    """The loss curve (and its running mean) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    steps = np.arange(1, len(losses) + 1)
    ax.plot(steps, losses, lw=0.6, alpha=0.4, label="batch loss")
    window = max(1, len(losses) // 50)
    if len(losses) >= window:
        smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
        ax.plot(steps[window - 1 :], smooth, lw=1.5, label=f"mean of {window}")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_title("SFT loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
