"""Training the pose estimator on twin episodes, and measuring it on any logged episodes.

The twin's episodes hold every object's true pose beside the cameras' frames, so
:func:`train_estimator` learns from as many placements as one cares to synthesize
(``twinrl expand --id N --ood N --detours 0.5`` in the twin whose look was fitted to
the cell). The backbone is frozen, so each frame's features are computed once and the
head trains on them. A tenth of the episodes is held out; the run stops at the step
count and keeps the weights that did best on them.

The held-out episodes' errors are reported per object: the median planar and 3-D
position errors (cm) and the orientation error (degrees; a round plate's turn is not
visible, so its figure says little). ``twinrl locate`` measures an estimator on any
logged episodes that hold the true poses (plant demos, evaluation rollouts), by the
TCP's distance to each object. Outputs of ``twinrl train perception``::

    out/config.json, out/model.safetensors   the estimator (PoseEstimator.from_pretrained)
    out/training.json                         settings, losses, held-out errors, seconds
    out/loss.png                              training and held-out losses
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from twinrl_data import schema as contract
from twinrl_data.atomic import write_text_atomic
from twinrl_data.sources import open_episodes
from twinrl_learn.compute import mixed_precision, module_device, resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.perception.estimator import EstimatorConfig, PoseEstimator, rotation_error_deg
from twinrl_learn.policy.inputs import relative_poses
from twinrl_learn.settings import PerceptionSettings

CAMERAS = ("front", "wrist")
PROPRIO_PREFIXES = ("tcp.", "gripper.")
FEATURE_BATCH = 128
HELD_OUT = 0.1
ROTATION_WEIGHT = 0.1  # rotation code errors against position errors in dm


@dataclass
class Frames:
    """Every frame of some episodes: what the estimator reads and its labels."""

    state: np.ndarray
    environment_state: np.ndarray
    images: dict[str, np.ndarray]
    episode: np.ndarray  # index of each frame's episode
    episodes: int
    state_names: list[str]
    environment_names: list[str]


def gather_frames(sources: Sequence[str | Path]) -> Frames:
    """Every frame of the episodes of ``sources`` (LeRobot datasets, sessions, catalogs),
    images as recorded (the estimator resizes them); episodes must hold the true object
    poses."""
    states, envs, episode_index = [], [], []
    images: dict[str, list[np.ndarray]] = {c: [] for c in CAMERAS}
    names: dict[str, list[str]] = {}
    for source in sources:
        episodes, _ = open_episodes(source)
        for episode in episodes:
            env = episode.data.get(contract.ENVIRONMENT_STATE)
            if env is None or np.isnan(np.asarray(env, np.float32)).any():
                raise LearnError(
                    f"{source}: episode {episode.meta.episode_id} holds no object poses; the "
                    "estimator learns and is measured on twin or plant episodes"
                )
            missing = [c for c in CAMERAS if c not in episode.images]
            if missing:
                raise LearnError(
                    f"{source}: episode {episode.meta.episode_id} has no camera(s) {missing}"
                )
            names = names or episode.meta.names
            states.append(np.asarray(episode.data[contract.STATE], np.float32))
            envs.append(np.asarray(env, np.float32))
            for camera in CAMERAS:
                images[camera].append(episode.images[camera])
            episode_index.append(np.full(len(episode), len(states) - 1))
    if not states:
        raise LearnError("the given sources hold no episodes")
    return Frames(
        state=np.concatenate(states),
        environment_state=np.concatenate(envs),
        images={c: np.concatenate(v) for c, v in images.items()},
        episode=np.concatenate(episode_index),
        episodes=len(states),
        state_names=list(names[contract.STATE]),
        environment_names=list(names[contract.ENVIRONMENT_STATE]),
    )


def object_layout(frames: Frames) -> tuple[list[str], list[int], int]:
    """The objects' names, where each ``<name>.x`` is in the environment state, and where
    ``tcp.x`` is in the state."""
    if "tcp.x" not in frames.state_names:
        raise LearnError("the episodes' state has no TCP pose (tcp.x ...)")
    indices = [i for i, n in enumerate(frames.environment_names) if n.endswith(".x")]
    if not indices:
        raise LearnError("the episodes' environment state has no object poses (<name>.x ...)")
    objects = [frames.environment_names[i].removesuffix(".x") for i in indices]
    return objects, indices, frames.state_names.index("tcp.x")


def targets(frames: Frames) -> torch.Tensor:
    """What the estimator should say of each frame (:func:`relative_poses`)."""
    _, indices, tcp_index = object_layout(frames)
    return relative_poses(
        torch.from_numpy(frames.state), torch.from_numpy(frames.environment_state),
        tcp_index, indices, orientations=True,
    )  # fmt: skip


def cached_features(
    estimator: PoseEstimator,
    frames: Frames,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Every frame's backbone features per camera, in half precision on the estimator's
    device (computed once: the backbone is frozen)."""
    device = module_device(estimator)
    total = len(frames.state) * len(estimator.config.cameras)
    done = 0

    def advance(images: int) -> None:
        nonlocal done
        done += images
        if progress is not None:
            progress(done, total)

    out = {}
    for camera in estimator.config.cameras:
        images = frames.images[camera]
        batches = (
            estimator.prepared(torch.from_numpy(images[start : start + FEATURE_BATCH]).to(device))
            for start in range(0, len(images), FEATURE_BATCH)
        )
        with mixed_precision(device):
            out[camera] = estimator.backbone.cached(batches, advance)
    return out


def new_estimator(frames: Frames, settings: PerceptionSettings, image_size: int) -> PoseEstimator:
    objects, _, _ = object_layout(frames)
    proprio = [n for n in frames.state_names if n.startswith(PROPRIO_PREFIXES)]
    columns = [frames.state_names.index(n) for n in proprio]
    values = frames.state[:, columns]
    torch.manual_seed(settings.seed)
    return PoseEstimator(
        EstimatorConfig(
            cameras=list(CAMERAS),
            objects=objects,
            proprio_names=proprio,
            state_names=frames.state_names,
            proprio_mean=values.mean(0).tolist(),
            proprio_std=np.maximum(values.std(0), 1e-3).tolist(),
            image_size=image_size,
            head_width=settings.head_width,
            seed=settings.seed,
            trained_on=[str(d) for d in settings.datasets],
        )
    )


def pose_loss(predicted: torch.Tensor, true: torch.Tensor, objects: int) -> torch.Tensor:
    """Squared position error (dm) plus ROTATION_WEIGHT times the rotation code's."""
    cut = 3 * objects
    position = F.mse_loss(predicted[:, :cut], true[:, :cut])
    return position + ROTATION_WEIGHT * F.mse_loss(predicted[:, cut:], true[:, cut:])


@dataclass
class PerceptionResult:
    out: Path
    steps: int
    losses: list[float] = field(default_factory=list)
    held_out: list[tuple[int, float]] = field(default_factory=list)
    held_out_errors: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0


def train_estimator(
    settings: PerceptionSettings,
    *,
    image_size: int = 128,
    progress: Callable[[str, int, int, dict[str, float]], None] | None = None,
) -> PerceptionResult:
    """Train a pose estimator (see the module docstring); ``progress(stage, done, total,
    metrics)`` reports the feature pass (``features``) and the training (``train``)."""
    out = Path(settings.out)
    if out.exists() and any(out.iterdir()):
        raise LearnError(f"{out} already exists and is not empty; choose another folder")
    started = time.perf_counter()
    device = resolve_device(settings.device)
    frames = gather_frames(settings.datasets)
    estimator = new_estimator(frames, settings, image_size).to(device)
    features = cached_features(
        estimator, frames, None if progress is None else lambda d, t: progress("features", d, t, {})
    )
    true = targets(frames).to(device)
    generator = torch.Generator().manual_seed(settings.seed)
    episodes = frames.episodes
    # A tenth of the episodes, at least one, held out (none when there is only one).
    count = max(1, round(HELD_OUT * episodes)) if episodes > 1 else 0
    held = torch.randperm(episodes, generator=generator)[:count]
    is_held = np.isin(frames.episode, held.numpy())
    train_rows = torch.from_numpy(np.flatnonzero(~is_held)).to(device)
    held_rows = torch.from_numpy(np.flatnonzero(is_held)).to(device)
    objects = len(estimator.config.objects)
    optimizer = torch.optim.AdamW(estimator.parameters(), lr=settings.lr, weight_decay=1e-4)
    state = torch.from_numpy(frames.state).to(device)
    losses: list[float] = []
    checks: list[tuple[int, float]] = []
    best, best_weights = math.inf, None
    estimator.train()
    for step in range(1, settings.steps + 1):
        pick = train_rows[
            torch.randint(0, len(train_rows), (settings.batch_size,), generator=generator)
        ]
        batch = {c: (f[pick], g[pick]) for c, (f, g) in features.items()}
        with mixed_precision(device):
            loss = pose_loss(estimator(batch, state[pick]).float(), true[pick], objects)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        for group in optimizer.param_groups:
            group["lr"] = settings.lr * 0.5 * (1 + math.cos(math.pi * (step - 1) / settings.steps))
        optimizer.step()
        losses.append(loss.item())
        if step % settings.log_every == 0 or step == settings.steps:
            held_loss = _loss_on(estimator, features, state, true, held_rows, objects)
            checks.append((step, held_loss))
            if held_loss < best:
                best = held_loss
                best_weights = {k: v.detach().clone() for k, v in estimator.state_dict().items()}
            if progress is not None:
                metrics = {"loss": float(np.mean(losses[-settings.log_every :])), "held": held_loss}
                progress("train", step, settings.steps, metrics)
    if best_weights is not None:
        estimator.load_state_dict(best_weights)
    estimator.eval()
    estimator.save_pretrained(out)
    held_errors = _errors_of_rows(estimator, features, state, true, held_rows)
    result = PerceptionResult(
        out, settings.steps, losses, checks, held_errors, time.perf_counter() - started
    )
    record = {
        "settings": asdict(settings),
        "frames": len(true),
        "episodes": episodes,
        "held_out_episodes": len(held),
        "held_out": checks,
        "held_out_errors": held_errors,
        "seconds": result.seconds,
    }
    write_text_atomic(out / "training.json", json.dumps(record, indent=1))
    plot_training(losses, checks, out / "loss.png")
    return result


@torch.no_grad()
def _predict(
    estimator: PoseEstimator,
    features: dict[str, tuple[torch.Tensor, torch.Tensor]],
    state: torch.Tensor,
    rows: torch.Tensor,
) -> torch.Tensor:
    was_training = estimator.training
    estimator.eval()
    parts = []
    for start in range(0, len(rows), 1024):
        pick = rows[start : start + 1024]
        batch = {c: (f[pick], g[pick]) for c, (f, g) in features.items()}
        with mixed_precision(state.device):
            parts.append(estimator(batch, state[pick]).float())
    estimator.train(was_training)
    return torch.cat(parts) if parts else torch.zeros(0, estimator.config.output_dim)


def _loss_on(
    estimator: PoseEstimator,
    features: dict[str, tuple[torch.Tensor, torch.Tensor]],
    state: torch.Tensor,
    true: torch.Tensor,
    rows: torch.Tensor,
    objects: int,
) -> float:
    """The pose loss on ``rows`` (NaN when there are none)."""
    if len(rows) == 0:
        return float("nan")
    return pose_loss(_predict(estimator, features, state, rows), true[rows], objects).item()


def _errors_of_rows(
    estimator: PoseEstimator,
    features: dict[str, tuple[torch.Tensor, torch.Tensor]],
    state: torch.Tensor,
    true: torch.Tensor,
    rows: torch.Tensor,
) -> dict[str, Any]:
    predicted = _predict(estimator, features, state, rows)
    return pose_errors(predicted, true[rows], estimator.config.objects)


def pose_errors(
    predicted: torch.Tensor, true: torch.Tensor, objects: list[str]
) -> dict[str, dict[str, float]]:
    """Per object: median planar and 3-D position errors (cm) and orientation error (deg)."""
    if len(true) == 0:
        nothing = {"planar_cm": math.nan, "position_cm": math.nan, "orientation_deg": math.nan}
        return {name: dict(nothing) for name in objects}
    out = {}
    k = len(objects)
    for i, name in enumerate(objects):
        delta = (predicted[:, 3 * i : 3 * i + 3] - true[:, 3 * i : 3 * i + 3]) * 10.0  # dm->cm
        code = slice(3 * k + 6 * i, 3 * k + 6 * i + 6)
        out[name] = {
            "planar_cm": float(delta[:, :2].norm(dim=-1).median()),
            "position_cm": float(delta.norm(dim=-1).median()),
            "orientation_deg": float(
                rotation_error_deg(predicted[:, code], true[:, code]).median()
            ),
        }
    return out


def plot_training(losses: list[float], checks: list[tuple[int, float]], path: Path) -> None:
    """Training loss (smoothed) and held-out loss against steps, on a log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    window = max(1, len(losses) // 100)
    smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
    ax.plot(np.arange(len(smooth)) + window, smooth, label="training")
    if checks:
        steps, values = zip(*checks, strict=True)
        ax.plot(steps, values, "o-", label="held-out episodes")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("pose loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
