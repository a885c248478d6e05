"""How well an image policy's locating head sees the objects, on any logged episodes.

An image policy trained with ``locate_weight`` says where each object is relative to
the TCP (:meth:`Policy.locate`). Its error on its own training frames says little: what
matters is the error on the frames its rollouts visit. :func:`locating_errors` replays
the logged frames of episodes that hold the true object poses (twin and plant episodes
do: demos, evaluations, RL) through the head and reports the error of each object's
position, by how far the TCP was from that object, per source and region::

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
from twinrl_learn.policy import Policy

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


def _object_names(policy: Policy, episode: contract.Episode) -> list[str]:
    names = episode.meta.names[contract.ENVIRONMENT_STATE]
    return [names[i].removesuffix(".x") for i in policy.config.object_indices]


@torch.no_grad()
def episode_errors(policy: Policy, episode: contract.Episode) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and object: the planar locating error and the TCP's distance to the
    object, both in cm, shapes (T, objects)."""
    state = np.asarray(episode.data[contract.STATE], np.float32)
    env = np.asarray(episode.data[contract.ENVIRONMENT_STATE], np.float32)
    located = []
    for start in range(0, len(state), BATCH):
        rows = slice(start, start + BATCH)
        batch = policy.inputs(
            state[rows],
            env[rows],
            {c: episode.images[c][rows] for c in policy.config.cameras},
            [episode.meta.instruction] * len(state[rows]),
        )
        located.append(policy.locate(batch).numpy())
    predicted = np.concatenate(located).reshape(len(state), -1, 3)
    true = policy.locating_targets(state, env)["objects"].numpy().reshape(len(state), -1, 3)
    # Offsets are in decimetres (Policy.relative_poses): x10 to cm.
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
    locating head; write ``locating.json`` and ``locating.png`` into ``out``.
    ``on_start(episodes)`` is called once the sources are opened, ``on_episode(label)``
    after each episode."""
    policy = Policy.from_pretrained(checkpoint)
    if not policy.locates:
        raise LearnError(
            f"{checkpoint} has no locating head: train the image policy (`policy` vla) with "
            "`locate_weight` above 0 on data holding object poses"
        )
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
            missing = [c for c in policy.config.cameras if c not in episode.images]
            if missing:
                raise LearnError(
                    f"{source}: episode {episode.meta.episode_id} has no camera(s) "
                    f"{', '.join(missing)}, which the policy reads"
                )
            error, distance = episode_errors(policy, episode)
            region = episode.meta.region or "all"
            per_object = results.setdefault(label, {}).setdefault(region, {})
            for k, name in enumerate(_object_names(policy, episode)):
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
    fig.suptitle(f"locating head of {Path(report['checkpoint']).name}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
