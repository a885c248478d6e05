"""The recorder every producer of episodes writes through.

Shaped like LeRobot's dataset writer: :meth:`Recorder.start_episode` with the
episode's metadata, :meth:`Recorder.add_frame` once per control step (a dict keyed by
contract field, see :mod:`twinrl_data.schema`), :meth:`Recorder.save_episode` at the
end. Frames stream straight into the episode's MCAP file (chunked, so a killed recorder
loses at most the last second); the target is a :class:`~twinrl_data.session.Session`
(which keeps its manifest current) or an :class:`EpisodeFolder` (loose files that a
parent process registers later, as parallel synthesis does).

    >>> recorder = Recorder(Session.create(path))          # doctest: +SKIP
    >>> recorder.start_episode(meta)                      # doctest: +SKIP
    >>> for frame in frames: recorder.add_frame(frame)    # doctest: +SKIP
    >>> recorder.save_episode()                           # doctest: +SKIP
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from twinrl_data.atomic import require_free_space
from twinrl_data.errors import DataError
from twinrl_data.mcap_log import EpisodeWriter
from twinrl_data.schema import EpisodeMeta
from twinrl_data.session import FREE_MARGIN
from twinrl_data.streams import LiveEpisode


class EpisodeTarget(Protocol):
    """Where a recorder puts episodes: opens one writer per episode."""

    def record(self, meta: EpisodeMeta, **writer_options: Any) -> EpisodeWriter: ...


class EpisodeFolder:
    """Episodes as loose files ``<folder>/<prefix><episode_id>.mcap``."""

    def __init__(self, folder: str | Path, prefix: str = "") -> None:
        self.folder, self.prefix = Path(folder), prefix

    def record(self, meta: EpisodeMeta, **writer_options: Any) -> EpisodeWriter:
        self.folder.mkdir(parents=True, exist_ok=True)
        require_free_space(self.folder, FREE_MARGIN, "recording an episode")
        return EpisodeWriter(
            self.folder / f"{self.prefix}{meta.episode_id}.mcap", meta, **writer_options
        )


class Recorder:
    """Records one episode at a time into ``target`` (see the module docstring)."""

    def __init__(self, target: EpisodeTarget, **writer_options: Any) -> None:
        self.target = target
        self.writer_options = writer_options
        self._writer: EpisodeWriter | None = None
        self.live: LiveEpisode | None = None  # the open episode's streams, when it has any
        self.saved_live: LiveEpisode | None = None  # the last saved one's (its counts, CPU)
        self.saved: EpisodeMeta | None = None  # the last saved episode's final metadata
        self.saved_path: Path | None = None  # and its file

    @property
    def recording(self) -> bool:
        """Whether an episode is open."""
        return self._writer is not None

    @property
    def frames(self) -> int:
        """Frames added to the open episode (0 when none is open)."""
        return self._writer.steps if self._writer is not None else 0

    def start_episode(
        self,
        meta: EpisodeMeta,
        *,
        cameras: Mapping[str, float] | None = None,
        samples: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        """Open an episode; with ``cameras`` (name -> fps) or ``samples`` (stream -> entry
        names) it is a live episode (:mod:`twinrl_data.streams`): those cameras' every
        frame and those sample streams go to :attr:`live`, and steps are written on the
        host's clock from a background thread."""
        if self._writer is not None:
            raise DataError(
                f"episode {self._writer.meta.episode_id} is still open; save_episode() first"
            )
        if not cameras and not samples:
            self._writer = self.target.record(meta, **self.writer_options)
            return
        self._writer = self.target.record(meta, **{**self.writer_options, "flush_seconds": 0})
        self.live = LiveEpisode(
            self._writer, cameras=cameras or {}, samples=samples or {}, started=time.monotonic()
        )

    def add_frame(self, frame: Mapping[str, Any], observed: float | None = None) -> None:
        """Write one control step; a frame that breaks the contract is an error naming
        every problem, and nothing of it is written. ``observed``: when its observation
        was taken (``time.monotonic()``; a live episode's clock, default now)."""
        writer = self._require_open()
        if self.live is not None:
            self.live.step(frame, time.monotonic() if observed is None else observed)
        else:
            writer.append(frame)

    def save_episode(
        self,
        *,
        success: bool | None = None,
        aborted: str | None = None,
        sensors: Mapping[str, Any] | None = None,
        note: str | None = None,
    ) -> Path:
        """Close the episode (``success`` defaults to the last frame's ``next.success``;
        ``aborted``: why it ended early; ``sensors``: what the cell's sensors delivered;
        ``note``: a person's words about it) and return its file."""
        writer = self._require_open()
        self._writer = None
        if self.live is not None:
            self.saved_live, self.live = self.live, None
            self.saved_live.close()
        self.saved = writer.close(success=success, aborted=aborted, sensors=sensors, note=note)
        self.saved_path = writer.path
        return writer.path

    def _require_open(self) -> EpisodeWriter:
        if self._writer is None:
            raise DataError("no episode is open; call start_episode(meta) first")
        return self._writer
