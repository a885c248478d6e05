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

``device`` picks where it trains (:mod:`twinrl_learn.compute`); the checkpoint loads on
any device. ``resume=True`` continues from ``training_state.pt`` exactly: the weights after N steps
are the same whether or not the run was interrupted (given the same ``steps``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from twinrl_data.errors import SettingError
from twinrl_data.training import FrameTable, load_frames
from twinrl_learn.compute import mixed_precision, resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.perception.estimator import PoseEstimator
from twinrl_learn.policy import Policy, PolicyConfig
from twinrl_learn.policy.close_height import demonstrated_close_height
from twinrl_learn.settings import STEM_STRIDES, SFTConfig
from twinrl_learn.training_state import load_state, save_state

# What a run saved before an option existed had: it did not locate objects, and it kept
# its learning rate constant.
SAVED_BEFORE_OPTION = {"locate_weight": 0.0, "lr_schedule": "constant"}


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
    estimates: torch.Tensor | None = None,
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """An augmented, normalised training batch of ``rows`` and their action chunks
    (``estimates``: every frame's pose estimates, for a policy that perceives)."""
    batch = policy.inputs(
        frames.state[rows],
        None if frames.environment_state is None else frames.environment_state[rows],
        {} if estimates is not None else {c: frames.images[c][rows] for c in frames.images},
        [frames.instruction[r] for r in rows],
        None if estimates is None else estimates[rows],
    )
    actions = policy.normalize("action", torch.from_numpy(frames.action_chunks(rows, chunk)))
    batch = policy.augment(batch, generator)
    actions = actions.to(policy.device, non_blocking=True)
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
        raise LearnError(f"{out} already holds a run; resume it or choose another folder")
    if resume and not state_file.is_file():
        raise LearnError(f"{state_file} does not exist: there is no run to resume")
    saved = load_state(state_file) if resume else None
    if saved is not None:
        _check_same_network(saved["config"], config.resolved(), out)
        config = _own_settings(config, saved["config"], out)
    config = config.resolved()
    device = resolve_device(config.device)
    weights = _given_weights(config, None if saved is None else saved["config"])
    frames = frames or _frames(config)
    if weights is None:  # as if the datasets were one
        weights = np.bincount(frames.source, minlength=len(config.datasets)) / len(frames.source)
    config = replace(config, weights=weights.tolist())
    estimator = (
        None
        if config.perception is None
        else PoseEstimator.from_pretrained(config.perception, device)
    )
    if estimator is not None and estimator.config.state_names != frames.state_names:
        raise LearnError(
            f"the pose estimator {config.perception} learnt on another observation.state "
            "layout than these datasets'; train one on twin episodes of this cell"
        )
    # Joint velocities are a clock in demonstrations that a rollout does not keep; relative
    # inputs (and a perceiving policy's, relative too) also leave out joint angles, which
    # would tell the policy where it is.
    relative = config.inputs == "relative" or estimator is not None
    ignored_state = ("qd.", "q.") if relative else ("qd.",)
    tcp_index = frames.state_names.index("tcp.x") if "tcp.x" in frames.state_names else -1
    object_indices = (
        [i for i, n in enumerate(frames.environment_names) if n.endswith(".x")]
        if tcp_index >= 0
        else []
    )
    if config.policy == "state" and not frames.environment_complete:
        raise LearnError(
            "the state policy reads object poses (observation.environment_state), which "
            "some dataset lacks; train the image policy (`policy` vla) on it, or leave that "
            "dataset out"
        )
    # Locating learns from the frames that hold the objects' true poses (twin and plant
    # data do; a real cell's demos may not); with none, the image policy learns from the
    # actions alone.
    locating = (
        config.policy == "vla"
        and estimator is None
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
        estimator=None if estimator is None else asdict(estimator.config),
        seed=config.seed,
        stats={k: {s: v.tolist() for s, v in d.items()} for k, d in frames.stats.items()},
    )
    policy = Policy(policy_config).to(device)
    estimates = None
    if estimator is not None:
        policy.estimator.load_state_dict(estimator.state_dict())
        # Computed once per frame (the backbone is frozen and an image pass is most of
        # the estimator's cost): what the policy trains on, as it will act on them.
        estimates = torch.from_numpy(estimator.estimate_rows(frames.images, frames.state))
    policy.config.close_height = _close_height(policy, frames, estimates)
    policy.reset()
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
        batch, actions = _batch(policy, frames, rows, generator, config.chunk, estimates)
        with mixed_precision(device):
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


def _close_height(
    policy: Policy, frames: FrameTable, estimates: torch.Tensor | None
) -> float | None:
    """How high over the object under it the demonstrations close the gripper, as the
    policy perceives the objects (:func:`demonstrated_close_height`); None for a policy
    that perceives none."""
    if not policy.perceives_objects:
        return None
    if estimates is not None:
        count = len(policy.estimator.config.objects)
    else:
        count = len(policy.config.object_indices)
        estimates = policy.relative_poses(
            torch.from_numpy(frames.state), torch.from_numpy(frames.environment_state)
        )
    offsets = estimates[:, : 3 * count].numpy().reshape(len(frames), count, 3) / 10.0
    return demonstrated_close_height(frames.action, frames.episode_end, offsets)


def learning_rate(config: SFTConfig, step: int) -> float:
    """The learning rate of update ``step`` (from 0): constant, or along a cosine from
    ``lr`` towards zero at the end of the run. A finished run resumed with more ``steps``
    jumps back up onto the longer cosine, so it does not end where a run of that length
    from scratch would."""
    if config.lr_schedule == "constant":
        return config.lr
    return config.lr * 0.5 * (1 + math.cos(math.pi * step / config.steps))


def _own_settings(config: SFTConfig, saved: dict, out: Path) -> SFTConfig:
    """A resumed run's own steps, batch size and learning rate where none are given. Other
    values, or other datasets, would not continue it exactly and are refused (only
    ``steps`` may differ: it extends the run)."""
    if len(config.datasets) != len(saved["datasets"]):
        raise LearnError(
            f"cannot resume {out}: it was trained on {len(saved['datasets'])} datasets, not "
            f"{len(config.datasets)}; resume it with the same ones"
        )
    own, differ = {}, []
    for key in ("batch_size", "lr", "lr_schedule"):
        saved_value = _saved_option(saved, key)
        given = getattr(config, key)
        if given is not None and given != saved_value:
            differ.append(f"`{key}` {saved_value}")
        own[key] = saved_value
    if differ:
        raise LearnError(
            f"cannot resume {out}: it was trained with {', '.join(differ)}; resume it without "
            "giving those"
        )
    return replace(config, steps=config.steps or saved["steps"], **own)


def _given_weights(config: SFTConfig, saved: dict | None) -> np.ndarray | None:
    """Each dataset's sampling probability from ``weights`` (normalised), or in a resumed
    run (``saved``: its config) the run's own (equal, for runs saved before they were
    recorded; other weights are refused); ``None``: in proportion to the datasets' frames."""
    count = len(config.datasets)
    if config.weights is not None and len(config.weights) != count:
        raise SettingError("weights", f"needs {count} values, one per dataset")
    given = None if config.weights is None else np.asarray(config.weights, np.float64)
    if given is not None and ((given < 0).any() or given.sum() == 0):
        raise SettingError("weights", "must be non-negative and not all zero")
    if saved is None:
        return None if given is None else given / given.sum()
    saved_weights = np.asarray(saved.get("weights") or [1.0] * count, np.float64)
    saved_weights = saved_weights / saved_weights.sum()
    if given is not None and not np.allclose(given / given.sum(), saved_weights):
        raise LearnError(
            f"cannot resume {config.out}: it was trained with `weights` "
            f"{','.join(f'{w:.4g}' for w in saved_weights)}; resume it without giving `weights`"
        )
    return saved_weights


def _saved_option(saved: dict, key: str):
    """Option ``key`` of a saved run's config; a run saved before the option existed had
    its SAVED_BEFORE_OPTION value, or else the field's default."""
    default = SFTConfig.__dataclass_fields__[key].default
    return saved.get(key, SAVED_BEFORE_OPTION.get(key, default))


def _check_same_network(saved: dict, config: SFTConfig, out: Path) -> None:
    """A resumed run must build the network it saved (else its weights do not fit)."""
    image_only = ("image_size", "locate_weight", "perception") if config.policy == "vla" else ()
    differ = []
    for key in ("policy", "chunk", "inputs", *image_only):
        before = _saved_option(saved, key)
        if before != getattr(config, key):
            differ.append((f"`{key}` {before}", str(getattr(config, key))))
    if differ:
        raise LearnError(
            f"cannot resume {out}: it was trained with {', '.join(d[0] for d in differ)}, not "
            f"{', '.join(d[1] for d in differ)}; resume it with the same settings"
        )


def _checkpoint(policy, optimizer, generator, step, losses, out: Path, config: SFTConfig) -> None:
    policy.save_pretrained(out / "checkpoints" / f"step_{step:06d}")
    save_state(
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
