"""Action chunks over a table of frames: which rows make up the chunk that starts at a
row (SFT's frame table and the RL replay buffer both index with it)."""

from __future__ import annotations

import numpy as np


def chunk_rows(
    rows: np.ndarray, episode_end: np.ndarray, chunk: int
) -> tuple[np.ndarray, np.ndarray]:
    """The rows of the action chunk that starts at each of ``rows``: ``(B, chunk)`` row
    indices, the episode's last row repeated past its end (``episode_end`` is each
    row's exclusive end row), and a mask of the entries inside the episode. Learners
    that execute chunks (SFT, Q-chunking RL) index their tables with it."""
    offsets = rows[:, None] + np.arange(chunk)[None]
    inside = offsets < episode_end[:, None]
    return np.minimum(offsets, episode_end[:, None] - 1), inside
