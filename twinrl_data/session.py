"""A recording session: a folder of episode MCAP files and a small manifest.

::

    SESSION/
      manifest.json                       # format, created_at, one entry per episode
      episodes/000000_<episode_id>.mcap   # one MCAP file per episode
      episodes/000001_<episode_id>.mcap
      .lock                               # who last changed the manifest

Every episode file carries its own metadata; the manifest is a cache of them (order,
status, length, success) that :func:`twinrl_data.repair.repair_session` can always
rebuild. Its changes are made under the session's lock (:mod:`twinrl_data.locking`),
each re-reading the manifest first, so several recorders may append to one session at
once, each episode under its own number. It is replaced atomically, fsynced, when an
episode starts (status ``recording``) and ends (``complete``, with length and
success). Readers never refuse a session whose manifest disagrees with its files: they
list what can be read and say what is wrong (:attr:`Session.problems`).
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import Any

from twinrl_data.atomic import owner_alive, owner_tag, require_free_space, write_atomic
from twinrl_data.errors import DataError, DataWarning
from twinrl_data.locking import FolderLock
from twinrl_data.mcap_log import EpisodeWriter, read_summary
from twinrl_data.schema import Episode, EpisodeMeta, image_field, now_iso

MANIFEST = "manifest.json"
FORMAT = "twinrl-session"
EPISODES = "episodes"
READABLE = ("complete", "recovered")  # statuses of episodes readers list
FREE_MARGIN = 256 * 2**20  # bytes that must be free before an episode starts
NUMBERED = re.compile(r"^(\d{6})_(.+)\.mcap$")


def is_session(path: str | Path) -> bool:
    path = Path(path)
    return (path / MANIFEST).is_file() or bool(episode_files(path))


def episode_files(folder: Path) -> list[Path]:
    """The episode files in a session's ``episodes/`` folder: numbered ones in number
    order, then any others (written by worker processes and registered) by name."""
    episodes = Path(folder) / EPISODES
    files = list(episodes.glob("*.mcap")) if episodes.is_dir() else []
    return sorted(files, key=lambda p: (0, p.name) if NUMBERED.match(p.name) else (1, p.name))


def entry_for(relative: str, meta: EpisodeMeta, status: str, length: int | None) -> dict:
    """A manifest entry for an episode file (``relative`` to the session folder)."""
    entry = {
        "file": relative,
        "episode_id": meta.episode_id,
        "task": meta.task,
        "source": meta.source,
        "world": meta.world,
        "created_at": meta.created_at,
        "status": status,
    }
    if length is not None:
        entry.update(length=length, success=meta.success)
    return entry


def entries_from_files(folder: Path) -> tuple[list[dict], list[str]]:
    """Manifest entries read from the episode files themselves, in number order, and
    what could not be read (one line each)."""
    entries, problems = [], []
    for path in episode_files(folder):
        relative = f"{EPISODES}/{path.name}"
        try:
            summary = read_summary(path)
        except DataError as err:
            problems.append(f"{relative} cannot be read: {err}")
            continue
        status = "complete" if summary.length is not None else "partial"
        entries.append(entry_for(relative, summary.meta, status, summary.length))
    return entries, problems


class Session:
    """Open an existing session (``Session(path)``) or make one (``Session.create``).

    ``min_free`` is the free disk space (bytes) an episode needs to start.
    """

    def __init__(self, path: str | Path, *, min_free: int = FREE_MARGIN) -> None:
        self.path = Path(path)
        self.min_free = min_free
        if not is_session(self.path):
            raise DataError(
                f"{self.path} is not a session (no {MANIFEST}); give a folder that episodes "
                "were recorded into, or create one with Session.create"
            )
        self.problems: list[str] = []
        self._finished_unlisted: list[Path] = []  # finished files the manifest misses
        self.manifest = self._load()

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
        if path.is_file():
            raise DataError(f"{path} is a file, not a folder; choose a new session folder")
        if path.exists() and any(path.iterdir()):
            raise DataError(
                f"{path} exists and is not an empty folder; choose a new session folder"
            )
        try:
            (path / EPISODES).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise DataError(f"cannot create the session folder {path} ({err.strerror})") from None
        with FolderLock(path):
            if not (path / MANIFEST).is_file():
                manifest = {"format": FORMAT, "version": 1, "created_at": now_iso(), "episodes": []}
                write_manifest(path, manifest)
        return cls(path)

    # ------------------------------------------------------------------ reading
    def _load(self) -> dict[str, Any]:
        """The manifest as it is on disk (rebuilt from the episode files when it is
        damaged or missing), with :attr:`problems` saying how it disagrees with them."""
        self.problems = []
        self._finished_unlisted = []
        manifest_path = self.path / MANIFEST
        try:
            manifest = read_manifest(self.path)
        except (OSError, ValueError) as err:
            reason = "missing" if not manifest_path.exists() else f"damaged ({err})"
            entries, unreadable = entries_from_files(self.path)
            self.problems.append(
                f"{manifest_path} is {reason}; its {len(entries)} episodes were read from their "
                f"files (`twinrl data repair {self.path}` rewrites it)"
            )
            self.problems += unreadable
            return {"format": FORMAT, "version": 1, "created_at": None, "episodes": entries}
        listed = {e["file"] for e in manifest["episodes"]}
        for entry in manifest["episodes"]:
            file = self.path / entry["file"]
            if not file.is_file():
                self.problems.append(f"{entry['file']} is listed but missing")
            elif entry.get("status") not in READABLE:
                if entry.get("recorder") and owner_alive(entry["recorder"]):
                    continue  # being recorded right now (its file is not read)
                if self._finished(file):
                    self._finished_unlisted.append(file)
                    continue  # the recorder finished it; only its entry was not updated
                self.problems.append(
                    f"{entry['file']} is {entry.get('status')}: its recorder stopped before "
                    f"finishing it (`twinrl data repair {self.path}` recovers it)"
                )
        orphans = [p for p in episode_files(self.path) if f"{EPISODES}/{p.name}" not in listed]
        if orphans:
            self._finished_unlisted += [p for p in orphans if self._finished(p)]
            self.problems.append(
                f"{len(orphans)} episode files are not in the manifest "
                f"({', '.join(p.name for p in orphans[:3])}{', ...' if len(orphans) > 3 else ''}"
                f"); `twinrl data repair {self.path}` adopts them"
            )
        return manifest

    @staticmethod
    def _finished(path: Path) -> bool:
        """Whether ``path`` is an episode file its recorder finished."""
        try:
            return read_summary(path).length is not None
        except DataError:
            return False

    def refresh(self) -> None:
        """Read the manifest again (other recorders may have added episodes)."""
        self.manifest = self._load()

    def warn(self) -> None:
        """Say every problem found as a :class:`~twinrl_data.errors.DataWarning`."""
        for problem in self.problems:
            warnings.warn(f"session {self.path}: {problem}", DataWarning, stacklevel=2)

    @property
    def entries(self) -> list[dict[str, Any]]:
        return list(self.manifest["episodes"])

    def episode_paths(self) -> list[Path]:
        """Episode files in recording order, every entry (see :meth:`readable_paths`)."""
        return [self.path / e["file"] for e in self.manifest["episodes"]]

    def readable_paths(self) -> list[Path]:
        """The files of the finished episodes: those the manifest lists as finished, in
        its order, then finished files it does not (see :attr:`problems`)."""
        listed = [
            self.path / e["file"]
            for e in self.manifest["episodes"]
            if e.get("status") in READABLE and (self.path / e["file"]).is_file()
        ]
        return listed + [p for p in self._finished_unlisted if p not in listed]

    # ------------------------------------------------------------------ writing
    def _change(self, change) -> Any:
        """Apply ``change`` to the manifest on disk under the session's lock."""
        with FolderLock(self.path):
            self.manifest = self._load()
            result = change(self.manifest["episodes"])
            self._save()
        return result

    def record(self, meta: EpisodeMeta, **writer_options: Any) -> EpisodeWriter:
        """Start recording an episode of this session; returns its :class:`EpisodeWriter`.

        Refused while less than ``min_free`` bytes are free. The episode takes the next
        free number (under the lock, so two recorders never share one)."""
        require_free_space(self.path, self.min_free, "recording an episode")

        def start(episodes: list[dict]) -> EpisodeWriter:
            taken = [
                int(m.group(1)) for e in episodes if (m := NUMBERED.match(Path(e["file"]).name))
            ]
            taken += [
                int(m.group(1))
                for p in (self.path / EPISODES).glob("*.mcap")
                if (m := NUMBERED.match(p.name))
            ]
            relative = f"{EPISODES}/{max(taken, default=-1) + 1:06d}_{meta.episode_id}.mcap"
            writer = EpisodeWriter(
                self.path / relative, meta, on_close=self._closed, **writer_options
            )
            started = entry_for(relative, meta, "recording", None)
            episodes.append(started | {"recorder": owner_tag()})
            return writer

        return self._change(start)

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
        folder = (self.path / EPISODES).resolve()
        if path.parent != folder or not path.is_file():
            raise DataError(f"{path} is not an episode file inside {folder}")
        self._change(
            lambda episodes: episodes.append(
                entry_for(f"{EPISODES}/{path.name}", meta, "complete", length)
            )
        )

    def truncate(self, keep: int) -> list[Path]:
        """Forget every episode after the first ``keep`` (e.g. a round an interrupted run
        did not finish): their files move to ``discarded/``, nothing is deleted."""

        def drop(episodes: list[dict]) -> list[Path]:
            moved = []
            if episodes[keep:]:
                (self.path / "discarded").mkdir(exist_ok=True)
            for entry in episodes[keep:]:
                source = self.path / entry["file"]
                if source.exists():
                    moved.append(source.replace(self.path / "discarded" / source.name))
            del episodes[keep:]
            return moved

        return self._change(drop)

    def discard(self, path: Path) -> Path:
        """Take one episode out of the session (a person discarded it to record it
        again): its file moves to ``discarded/`` and its entry leaves the manifest;
        nothing is deleted. Returns where the file went."""
        relative = f"{EPISODES}/{Path(path).name}"

        def drop(episodes: list[dict]) -> Path:
            (self.path / "discarded").mkdir(exist_ok=True)
            moved = (self.path / relative).replace(self.path / "discarded" / Path(path).name)
            episodes[:] = [e for e in episodes if e["file"] != relative]
            return moved

        if not (self.path / relative).is_file():
            raise DataError(f"{relative} is not an episode file of session {self.path}")
        return self._change(drop)

    def _closed(self, meta: EpisodeMeta, length: int, status: str) -> None:
        def close(episodes: list[dict]) -> None:
            for entry in episodes:
                if entry["episode_id"] == meta.episode_id:
                    entry.update(status=status, length=length, success=meta.success)
                    entry.pop("recorder", None)

        self._change(close)

    def _save(self) -> None:
        write_manifest(self.path, self.manifest)


def read_manifest(folder: Path) -> dict[str, Any]:
    """A session's manifest as written; ``ValueError`` when it is not one (damaged)."""
    manifest = json.loads((Path(folder) / MANIFEST).read_text())
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError("not a twinrl session manifest")
    if not isinstance(manifest.get("episodes"), list):
        raise ValueError("no episode list")
    for number, entry in enumerate(manifest["episodes"]):
        if not _well_formed(entry):
            raise ValueError(f"entry {number} is malformed")
    return manifest


def write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    """Replace a session's manifest whole (see :func:`twinrl_data.atomic.write_atomic`)."""
    write_atomic(Path(folder) / MANIFEST, json.dumps(manifest, indent=1).encode())


def _well_formed(entry: Any) -> bool:
    """Whether a manifest entry names an episode file of the session, with an id."""
    if not isinstance(entry, dict):
        return False
    file, ident = entry.get("file"), entry.get("episode_id")
    return (
        isinstance(file, str)
        and isinstance(ident, str)
        and file.startswith(f"{EPISODES}/")
        and "/" not in file[len(EPISODES) + 1 :]
        and file.endswith(".mcap")
        and ".." not in file
    )
