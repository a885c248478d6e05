"""Reading datasets for training: batches from one or more LeRobotDatasets.

Learners read LeRobotDatasets through lerobot itself; this module only puts several of
them behind one PyTorch ``DataLoader`` and checks that they agree.

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
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import ConcatDataset, DataLoader

from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import open_dataset


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
