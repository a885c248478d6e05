"""A recording session: a folder of episode MCAP files and a small manifest.

::

    SESSION/
      manifest.json                       # format, created_at, one entry per episode
      episodes/000000_<episode_id>.mcap   # one MCAP file per episode
      episodes/000001_<episode_id>.mcap

The manifest is rewritten atomically when an episode starts (status ``recording``) and
when it ends (``complete``, with length and success), so a crash leaves it consistent.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from twinrl_data.errors import DataError
from twinrl_data.mcap_log import EpisodeWriter
from twinrl_data.schema import Episode, EpisodeMeta, image_field, now_iso

MANIFEST = "manifest.json"
FORMAT = "twinrl-session"


def is_session(path: str | Path) -> bool:
    return (Path(path) / MANIFEST).is_file()


class Session:
    """Open an existing session (``Session(path)``) or make one (``Session.create``)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        manifest = self.path / MANIFEST
        if not manifest.is_file():
            raise DataError(
                f"{self.path} is not a session (no {MANIFEST}); give a folder that episodes were "
                "recorded into, or create one with Session.create"
            )
        try:
            self.manifest: dict[str, Any] = json.loads(manifest.read_text())
        except json.JSONDecodeError as err:
            raise DataError(
                f"{manifest} is not valid JSON ({err.msg}); the session is damaged"
            ) from None
        if self.manifest.get("format") != FORMAT:
            raise DataError(f"{manifest} is not a twinrl session manifest")

    @classmethod
    def create(cls, path: str | Path, *, exist_ok: bool = False) -> Session:
        """Make a new session folder, or reopen it when ``exist_ok`` and it is a session."""
        path = Path(path)
        if is_session(path):
            if exist_ok:
                return cls(path)
            raise DataError(
                f"session {path} already exists; choose another folder or add episodes to "
                "it (`append`)"
            )
        if path.exists() and any(path.iterdir()):
            raise DataError(
                f"{path} exists and is not an empty folder; choose a new session folder"
            )
        (path / "episodes").mkdir(parents=True, exist_ok=True)
        _write_json(
            path / MANIFEST,
            {"format": FORMAT, "version": 1, "created_at": now_iso(), "episodes": []},
        )
        return cls(path)

    @property
    def entries(self) -> list[dict[str, Any]]:
        return list(self.manifest["episodes"])

    def episode_paths(self) -> list[Path]:
        """Episode files in recording order."""
        return [self.path / e["file"] for e in self.manifest["episodes"]]

    def record(self, meta: EpisodeMeta, **writer_options: Any) -> EpisodeWriter:
        """Start recording an episode of this session; returns its :class:`EpisodeWriter`."""
        index = len(self.manifest["episodes"])
        relative = f"episodes/{index:06d}_{meta.episode_id}.mcap"
        entry = {
            "file": relative,
            "episode_id": meta.episode_id,
            "task": meta.task,
            "source": meta.source,
            "world": meta.world,
            "created_at": meta.created_at,
            "status": "recording",
        }
        writer = EpisodeWriter(self.path / relative, meta, on_close=self._closed, **writer_options)
        self.manifest["episodes"].append(entry)
        self._save()
        return writer

    def add(self, episode: Episode) -> Path:
        """Write a whole in-memory episode into this session; returns its file."""
        with self.record(episode.meta) as log:
            for t in range(len(episode)):
                step = {key: values[t] for key, values in episode.data.items()}
                step.update({image_field(c): f[t] for c, f in episode.images.items()})
                log.append(step)
        return log.path

    def register(self, path: Path, meta: EpisodeMeta, length: int) -> None:
        """Add an episode file written elsewhere (e.g. by a worker process) to the manifest.

        The file must already be inside this session's ``episodes/`` folder.
        """
        path = Path(path).resolve()
        folder = (self.path / "episodes").resolve()
        if path.parent != folder or not path.is_file():
            raise DataError(f"{path} is not an episode file inside {folder}")
        self.manifest["episodes"].append(
            {
                "file": f"episodes/{path.name}",
                "episode_id": meta.episode_id,
                "task": meta.task,
                "source": meta.source,
                "world": meta.world,
                "created_at": meta.created_at,
                "status": "complete",
                "length": length,
                "success": meta.success,
            }
        )
        self._save()

    def truncate(self, keep: int) -> list[Path]:
        """Forget every episode after the first ``keep`` (e.g. a round an interrupted run
        did not finish): their files move to ``discarded/``, nothing is deleted."""
        dropped = self.manifest["episodes"][keep:]
        moved = []
        if dropped:
            (self.path / "discarded").mkdir(exist_ok=True)
            for entry in dropped:
                source = self.path / entry["file"]
                if source.exists():
                    moved.append(source.replace(self.path / "discarded" / source.name))
            self.manifest["episodes"] = self.manifest["episodes"][:keep]
            self._save()
        return moved

    def _closed(self, meta: EpisodeMeta, length: int) -> None:
        for entry in self.manifest["episodes"]:
            if entry["episode_id"] == meta.episode_id:
                entry.update(status="complete", length=length, success=meta.success)
        self._save()

    def _save(self) -> None:
        _write_json(self.path / MANIFEST, self.manifest)


def _write_json(path: Path, data: dict[str, Any]) -> None:
    """Write atomically: a crash leaves the old or the new file, never half of one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".manifest-")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)
