"""How well an image policy's locating head, or a pose estimator, sees the objects on
any logged episodes.

An image policy trained with ``locate_weight`` says where each object is relative to
the TCP (:meth:`Policy.locate`); a pose estimator (:mod:`twinrl_learn.perception`),
alone or inside the image policy that acts through it, says the same. Its error on its
own training frames says little: what matters is the error on the frames its rollouts
visit. :func:`locating_errors` replays the logged frames of episodes that hold the true
object poses (twin and plant episodes do: demos, evaluations, RL) through it and reports
the error of each object's position, by how far the TCP was from that object, per
source and region::

    out/locating.json   {"checkpoint", "bands_cm", "sources": {label: {region: {object:
                         {"frames": [...], "median_cm": [...], "first_frame_cm": x,
                          "episodes": n}}}}}
    out/locating.png    median error against distance, one line per source and region

The errors are in the table plane (x, y), where a grasp must land.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from twinrl_data import schema as contract
from twinrl_data.atomic import write_text_atomic
from twinrl_data.sources import open_episodes
from twinrl_learn.errors import LearnError
from twinrl_learn.perception.estimator import PoseEstimator
from twinrl_learn.policy import Policy
from twinrl_learn.policy.checkpoint import is_checkpoint
from twinrl_learn.policy.inputs import relative_poses

# TCP-to-object distances (cm) that split the frames: grasping, approaching, reaching.
BANDS_CM = (0.0, 5.0, 10.0, 20.0, np.inf)
BATCH = 256


@dataclass
class ObjectErrors:
    """One object's planar locating errors (cm) and the TCP's distance to it (cm) in
    every frame, with each episode's first frame marked."""

    distance_cm: list[np.ndarray] = field(default_factory=list)
    error_cm: list[np.ndarray] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        distance, error = np.concatenate(self.distance_cm), np.concatenate(self.error_cm)
        frames, medians = [], []
        for low, high in itertools.pairwise(BANDS_CM):
            inside = (distance >= low) & (distance < high)
            frames.append(int(inside.sum()))
            medians.append(float(np.median(error[inside])) if inside.any() else None)
        return {
            "frames": frames,
            "median_cm": medians,
            "first_frame_cm": float(np.median([e[0] for e in self.error_cm])),
            "episodes": len(self.error_cm),
        }


class Locator:
    """Where a model sees each object relative to the TCP: an image policy's locating
    head, a pose estimator (:mod:`twinrl_learn.perception`), or the estimator an image
    policy acts through."""

    def __init__(self, model: Policy | PoseEstimator) -> None:
        if isinstance(model, Policy) and model.perceives:
            model = model.estimator
        if isinstance(model, Policy) and not model.locates:
            raise LearnError(
                "this policy neither locates the objects nor acts through a pose estimator: "
                "train the image policy (`policy` vla) with `locate_weight` above 0 on data "
                "holding object poses, or with `perception`"
            )
        self.model = model

    @classmethod
    def load(cls, path: str | Path) -> Locator:
        """From a policy checkpoint or a pose estimator folder."""
        if is_checkpoint(path):
            return cls(Policy.from_pretrained(path))
        return cls(PoseEstimator.from_pretrained(path))

    @property
    def cameras(self) -> list[str]:
        return list(self.model.config.cameras)

    def object_indices(self, names: list[str]) -> list[int]:
        """Where each located object's ``<name>.x`` is in an episode's environment state."""
        if isinstance(self.model, Policy):
            return list(self.model.config.object_indices)
        missing = [o for o in self.model.config.objects if f"{o}.x" not in names]
        if missing:
            raise LearnError(f"the episodes hold no pose of {', '.join(missing)}")
        return [names.index(f"{o}.x") for o in self.model.config.objects]

    def __call__(
        self,
        state: np.ndarray,
        env: np.ndarray,
        images: dict[str, np.ndarray],
        instructions: list[str],
    ) -> np.ndarray:
        """Located offsets (B, 3 x objects) in decimetres along the base axes."""
        if isinstance(self.model, PoseEstimator):
            located = self.model.estimate(images, state)
            return located[:, : 3 * len(self.model.config.objects)].numpy()
        batch = self.model.inputs(state, env, images, instructions)
        return self.model.locate(batch).numpy()


def _object_names(episode: contract.Episode, indices: list[int]) -> list[str]:
    names = episode.meta.names[contract.ENVIRONMENT_STATE]
    return [names[i].removesuffix(".x") for i in indices]


@torch.no_grad()
def episode_errors(
    model: Policy | Locator, episode: contract.Episode
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and object: the planar locating error and the TCP's distance to the
    object, both in cm, shapes (T, objects)."""
    locator = model if isinstance(model, Locator) else Locator(model)
    state = np.asarray(episode.data[contract.STATE], np.float32)
    env = np.asarray(episode.data[contract.ENVIRONMENT_STATE], np.float32)
    names = episode.meta.names
    indices = locator.object_indices(list(names[contract.ENVIRONMENT_STATE]))
    located = []
    for start in range(0, len(state), BATCH):
        rows = slice(start, start + BATCH)
        located.append(
            locator(
                state[rows],
                env[rows],
                {c: episode.images[c][rows] for c in locator.cameras},
                [episode.meta.instruction] * len(state[rows]),
            )
        )
    predicted = np.concatenate(located).reshape(len(state), -1, 3)
    tcp_index = list(names[contract.STATE]).index("tcp.x")
    true = relative_poses(
        torch.from_numpy(state), torch.from_numpy(env), tcp_index, indices, orientations=False
    )
    true = true.numpy().reshape(len(state), -1, 3)
    # Offsets are in decimetres (relative_poses): x10 to cm.
    error = np.linalg.norm(predicted[..., :2] - true[..., :2], axis=-1) * 10.0
    distance = np.linalg.norm(true, axis=-1) * 10.0
    return error, distance


def locating_errors(
    checkpoint: str | Path,
    sources: dict[str, Path],
    out: str | Path,
    on_episode: Callable[[str], None] | None = None,
    on_start: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Replay every episode of ``sources`` (label -> folder) through the checkpoint's
    locating head or pose estimator (:class:`Locator`); write ``locating.json`` and
    ``locating.png`` into ``out``.
    ``on_start(episodes)`` is called once the sources are opened, ``on_episode(label)``
    after each episode."""
    try:
        locator = Locator.load(checkpoint)
    except LearnError as error:
        raise LearnError(f"{checkpoint}: {error}") from None
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise LearnError(f"{out} exists and is not empty; choose another output folder")
    opened = {label: open_episodes(Path(source)) for label, source in sources.items()}
    if on_start is not None:
        on_start(sum(count for _, count in opened.values()))
    results: dict[str, dict[str, dict[str, ObjectErrors]]] = {}
    for label, source in sources.items():
        for episode in opened[label][0]:
            if contract.ENVIRONMENT_STATE not in episode.data:
                raise LearnError(
                    f"{source}: episode {episode.meta.episode_id} has no "
                    f"{contract.ENVIRONMENT_STATE}; the error needs the objects' true poses "
                    "(twin and plant episodes have them)"
                )
            missing = [c for c in locator.cameras if c not in episode.images]
            if missing:
                raise LearnError(
                    f"{source}: episode {episode.meta.episode_id} has no camera(s) "
                    f"{', '.join(missing)}, which the policy reads"
                )
            error, distance = episode_errors(locator, episode)
            region = episode.meta.region or "all"
            per_object = results.setdefault(label, {}).setdefault(region, {})
            indices = locator.object_indices(episode.meta.names[contract.ENVIRONMENT_STATE])
            for k, name in enumerate(_object_names(episode, indices)):
                errors = per_object.setdefault(name, ObjectErrors())
                errors.error_cm.append(error[:, k])
                errors.distance_cm.append(distance[:, k])
            if on_episode is not None:
                on_episode(label)
    report = {
        "checkpoint": str(checkpoint),
        "bands_cm": [b if np.isfinite(b) else None for b in BANDS_CM],
        "sources": {
            label: {
                region: {name: errors.summary() for name, errors in objects.items()}
                for region, objects in regions.items()
            }
            for label, regions in results.items()
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "locating.json", json.dumps(report, indent=1))
    plot_locating(report, out / "locating.png")
    return report


def band_labels(bands: list[float | None]) -> list[str]:
    """'0-5', '5-10', ..., '20+' (cm) for the report's bands."""
    return [
        f"{low:g}-{high:g}" if high is not None else f"{low:g}+"
        for low, high in itertools.pairwise(bands)
    ]


def plot_locating(report: dict[str, Any], path: Path) -> None:
    """Median planar error against the TCP's distance to the object, one panel per
    object, one line per source and region."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objects = sorted(
        {
            name
            for regions in report["sources"].values()
            for per_object in regions.values()
            for name in per_object
        }
    )
    labels = band_labels(report["bands_cm"])
    fig, axes = plt.subplots(
        1, len(objects), figsize=(4.5 * len(objects), 3.6), dpi=120, squeeze=False
    )
    for ax, name in zip(axes[0], objects, strict=True):
        for label, regions in report["sources"].items():
            for region, per_object in regions.items():
                if name not in per_object:
                    continue
                medians = [np.nan if m is None else m for m in per_object[name]["median_cm"]]
                ax.plot(labels, medians, marker="o", label=f"{label} ({region})")
        ax.set_title(name)
        ax.set_xlabel("TCP to object (cm)")
        ax.set_ylabel("median planar error (cm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"where {Path(report['checkpoint']).name} sees the objects", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
