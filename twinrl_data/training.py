"""Reading datasets for training: batches from one or more LeRobotDatasets.

Two ways in, both through lerobot's reader:

- :func:`make_dataloader`: several LeRobotDatasets behind one PyTorch ``DataLoader``,
  frames decoded on demand (any size of dataset);
- :func:`load_frames`: every frame decoded once into memory (a 100-episode dataset with
  two 64x64 cameras is ~50 MB), which is what fast SFT on a small machine needs.

``delta_timestamps`` asks for windows around each frame, as in lerobot: ``{"action":
[0.0, 0.1, 0.2]}`` returns the action at t, t + 0.1 s and t + 0.2 s (an action chunk),
with ``action_is_pad`` marking steps past the episode's end.

    >>> loader = make_dataloader(["data/pick_place"], batch_size=32,
    ...                          delta_timestamps={"action": [0.0, 0.1, 0.2]})  # doctest: +SKIP
    >>> batch = next(iter(loader))                                               # doctest: +SKIP
    >>> batch["action"].shape                                                    # doctest: +SKIP
    torch.Size([32, 3, 7])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import PIL.Image
import torch
from torch.utils.data import ConcatDataset, DataLoader

from twinrl_data.chunks import chunk_rows
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import iter_dataset_episodes, open_dataset
from twinrl_data.schema import ACTION, ENVIRONMENT_STATE, STATE


def training_dataset(
    roots: Sequence[str | Path],
    *,
    delta_timestamps: dict[str, list[float]] | None = None,
) -> ConcatDataset:
    """The frames of every dataset in ``roots`` as one map-style dataset.

    All datasets must have the same fps and the same features (names, dtypes, shapes);
    the error lists what differs.
    """
    if not roots:
        raise DataError("no dataset given; pass at least one LeRobotDataset folder")
    datasets = [open_dataset(root, delta_timestamps=delta_timestamps) for root in roots]
    reference = datasets[0].meta
    for root, dataset in zip(roots[1:], datasets[1:], strict=True):
        if dataset.meta.fps != reference.fps:
            raise DataError(f"{root} runs at {dataset.meta.fps} fps, {roots[0]} at {reference.fps}")
        shapes = {k: (v["dtype"], tuple(v["shape"])) for k, v in dataset.meta.features.items()}
        expected = {k: (v["dtype"], tuple(v["shape"])) for k, v in reference.features.items()}
        if shapes != expected:
            differ = sorted(
                k for k in shapes.keys() | expected.keys() if shapes.get(k) != expected.get(k)
            )
            raise DataError(f"{root} and {roots[0]} differ in features {differ}")
    return ConcatDataset(datasets)


def make_dataloader(
    roots: Sequence[str | Path],
    *,
    batch_size: int = 32,
    delta_timestamps: dict[str, list[float]] | None = None,
    shuffle: bool = True,
    seed: int = 0,
    num_workers: int = 0,
    drop_last: bool = False,
) -> DataLoader[dict[str, Any]]:
    """A ``DataLoader`` of training batches (dicts of tensors) over ``roots``.

    Deterministic for a given ``seed``; images come as float tensors in [0, 1], C x H x W.
    """
    dataset = training_dataset(roots, delta_timestamps=delta_timestamps)
    generator = torch.Generator().manual_seed(seed)
    return DataLoader(
        dataset,
        batch_size=batch_size,
        shuffle=shuffle,
        generator=generator,
        num_workers=num_workers,
        drop_last=drop_last,
    )


@dataclass
class FrameTable:
    """Every frame of one or more datasets, decoded once and held in memory.

    Arrays have one row per frame; ``episode_end[i]`` is the exclusive end row of frame
    ``i``'s episode (for action chunks), ``source[i]`` the index of its dataset in
    ``roots``. Images are uint8 (N, S, S, 3) at ``image_size``. ``environment_state``
    is None when no episode holds object poses, and NaN in the rows of episodes that do
    not (a real cell's demos mixed with the twin's); :attr:`environment_complete` says
    whether every row has them.
    """

    roots: list[Path]
    state: np.ndarray
    environment_state: np.ndarray | None
    action: np.ndarray
    images: dict[str, np.ndarray]
    instruction: list[str]
    episode_end: np.ndarray
    source: np.ndarray
    stats: dict[str, dict[str, np.ndarray]]
    state_names: list[str]
    environment_names: list[str]

    def __len__(self) -> int:
        return len(self.state)

    @property
    def environment_complete(self) -> bool:
        """Whether every frame holds observation.environment_state."""
        env = self.environment_state
        return env is not None and not np.isnan(env).any()

    def action_chunks(self, rows: np.ndarray, chunk: int) -> np.ndarray:
        """Actions rows..rows+chunk-1 of each row's episode, the last repeated past its end."""
        return self.action[chunk_rows(rows, self.episode_end[rows], chunk)[0]]


def load_frames(
    roots: Sequence[str | Path],
    *,
    cameras: Sequence[str] = (),
    image_size: int | None = None,
) -> FrameTable:
    """Decode the datasets in ``roots`` into a :class:`FrameTable` (what SFT trains on).

    Only the listed ``cameras`` are decoded (none for state policies); images are
    resized to ``image_size`` x ``image_size`` on load when given. Statistics are
    computed over all frames: mean/std for states, min/max for actions.
    """
    if not roots:
        raise DataError("no dataset given; pass at least one LeRobotDataset folder")
    states, envs, actions, instructions, ends, sources = [], [], [], [], [], []
    images: dict[str, list[np.ndarray]] = {c: [] for c in cameras}
    total = 0
    names: dict[str, list[str]] = {}
    for index, root in enumerate(roots):
        for episode in iter_dataset_episodes(root, cameras=list(cameras)):
            names = names or episode.meta.names
            missing = [c for c in cameras if c not in episode.images]
            if missing:
                raise DataError(f"{root} has no camera(s) {missing}; it has {episode.cameras}")
            n = len(episode)
            states.append(episode.data[STATE])
            envs.append(episode.data.get(ENVIRONMENT_STATE))
            actions.append(episode.data[ACTION])
            instructions.extend([episode.meta.instruction or episode.meta.task] * n)
            total += n
            ends.append(np.full(n, total))
            sources.append(np.full(n, index))
            for camera in cameras:
                frames = episode.images[camera]
                if image_size is not None and frames.shape[1] != image_size:
                    frames = np.stack(
                        [
                            np.asarray(
                                PIL.Image.fromarray(f).resize(
                                    (image_size, image_size), PIL.Image.BILINEAR
                                )
                            )
                            for f in frames
                        ]
                    )
                images[camera].append(frames)
    if total == 0:
        raise DataError(f"the datasets {list(map(str, roots))} hold no frames")
    state = np.concatenate(states).astype(np.float32)
    action = np.concatenate(actions).astype(np.float32)
    width = next((e.shape[1] for e in envs if e is not None), None)
    env = None
    if width is not None:
        env = np.concatenate(
            [
                np.full((len(s), width), np.nan) if e is None else e
                for s, e in zip(states, envs, strict=True)
            ]
        ).astype(np.float32)
    stats = {
        "state": {"mean": state.mean(0), "std": state.std(0) + 1e-3},
        "action": {"min": action.min(0), "max": action.max(0)},
    }
    if env is not None:
        stats["env"] = {"mean": np.nanmean(env, 0), "std": np.nanstd(env, 0) + 1e-3}
    return FrameTable(
        roots=[Path(r) for r in roots],
        state=state,
        environment_state=env,
        action=action,
        images={c: np.concatenate(v) for c, v in images.items()},
        instruction=instructions,
        episode_end=np.concatenate(ends),
        source=np.concatenate(sources),
        stats=stats,
        state_names=list(names.get(STATE, [])),
        environment_names=list(names.get(ENVIRONMENT_STATE, [])),
    )
