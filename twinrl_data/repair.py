"""Repair and verify sessions: the manifest rebuilt from the episode files, every file
checked.

- :func:`repair_session` rewrites a session's manifest from its episode files (which
  carry their own metadata): orphans adopted, missing files reported, unfinished or
  damaged episodes recovered (:func:`twinrl_data.salvage.recover`), the originals kept
  under ``damaged/``. Nothing is deleted.
- :func:`verify` checks a session, an episode file or a LeRobot dataset the way
  ``git fsck`` checks a repository and lists every problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from twinrl_data.atomic import owner_alive
from twinrl_data.errors import DataError
from twinrl_data.locking import FolderLock
from twinrl_data.mcap_log import read_episode, read_summary
from twinrl_data.salvage import check_episode_file, recover
from twinrl_data.session import (
    EPISODES,
    FORMAT,
    READABLE,
    Session,
    entry_for,
    episode_files,
    is_session,
    read_manifest,
    write_manifest,
)

DAMAGED = "damaged"


@dataclass
class Repair:
    """What :func:`repair_session` did."""

    episodes: int = 0  # listed in the new manifest
    adopted: list[str] = field(default_factory=list)  # files the old manifest lacked
    missing: list[str] = field(default_factory=list)  # listed files that are gone
    recovered: list[str] = field(default_factory=list)  # unfinished/damaged, salvaged
    empty: list[str] = field(default_factory=list)  # unfinished before a whole step
    busy: list[str] = field(default_factory=list)  # still being recorded: left alone
    unreadable: list[str] = field(default_factory=list)  # nothing could be salvaged
    manifest_was: str = "consistent"  # consistent, damaged, missing


def repair_session(path: str | Path) -> Repair:
    """Rebuild ``path``'s manifest from its episode files (see the module docstring)."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path} is not a folder; give a session folder")
    if not is_session(path):
        raise DataError(f"{path} holds no manifest and no episode files: not a session")
    report = Repair()
    with FolderLock(path):
        old = _old_manifest(path, report)
        listed = {e["file"]: e for e in old.get("episodes", [])}
        on_disk = {f"{EPISODES}/{p.name}": p for p in episode_files(path)}
        report.missing = sorted(f for f in listed if f not in on_disk)
        entries = []
        for relative, file in on_disk.items():
            if relative not in listed and report.manifest_was == "consistent":
                report.adopted.append(relative)
            recorder = listed.get(relative, {}).get("recorder")
            if (
                listed.get(relative, {}).get("status") == "recording"
                and recorder
                and (owner_alive(recorder))
            ):
                entries.append(listed[relative])  # still being recorded: left alone
                report.busy.append(f"{relative} (process {recorder})")
                continue
            entry = _entry(path, relative, file, report)
            if entry is not None:
                entries.append(entry)
        manifest = {
            "format": FORMAT,
            "version": 1,
            "created_at": old.get("created_at"),
            "episodes": entries,
        }
        write_manifest(path, manifest)
        report.episodes = len(entries)
    return report


def _old_manifest(path: Path, report: Repair) -> dict:
    try:
        return read_manifest(path)
    except FileNotFoundError:
        report.manifest_was = "missing"
    except (OSError, ValueError):
        report.manifest_was = "damaged"
    return {}


def _entry(path: Path, relative: str, file: Path, report: Repair) -> dict | None:
    """The manifest entry of one episode file, after salvaging it when it needs it."""
    problems = check_episode_file(file)
    if not problems:
        summary = read_summary(file)
        return entry_for(relative, summary.meta, "complete", summary.length)
    (path / DAMAGED).mkdir(exist_ok=True)
    kept = path / DAMAGED / file.name
    salvaged = file.with_name(file.name.replace(".mcap", ".recovered.mcap"))
    try:
        recover(file, salvaged, force=True)
        meta = read_summary(salvaged).meta
        length = len(read_episode(salvaged, images=False))
    except DataError as err:
        salvaged.unlink(missing_ok=True)
        file.replace(kept)
        empty = "no complete step" in str(err)
        (report.empty if empty else report.unreadable).append(f"{relative} (moved to {DAMAGED}/)")
        return None
    file.replace(kept)
    salvaged.replace(file)  # the salvaged episode takes the original's place and number
    report.recovered.append(relative)
    return entry_for(relative, meta, "recovered", length)


@dataclass
class Verification:
    """What :func:`verify` found: ``checked`` files, ``problems`` one line each."""

    checked: int = 0
    problems: list[str] = field(default_factory=list)


def verify(path: str | Path) -> Verification:
    """Check a session folder, an episode ``.mcap`` or a LeRobot dataset folder."""
    path = Path(path)
    result = Verification()
    if path.suffix == ".mcap" and path.is_file():
        result.checked = 1
        result.problems = check_episode_file(path)
    elif path.is_dir() and is_session(path):
        session = Session(path)
        result.problems += [f"session {path}: {p}" for p in session.problems]
        for entry in session.entries:
            file = path / entry["file"]
            if not file.is_file():
                continue  # reported as missing above
            result.checked += 1
            found = check_episode_file(file)
            result.problems += found
            if not found and entry.get("status") in READABLE:
                summary = read_summary(file)
                if summary.meta.episode_id != entry.get("episode_id") or (
                    entry.get("length") is not None and summary.length != entry["length"]
                ):
                    result.problems.append(
                        f"{entry['file']}: the manifest's entry disagrees with the file "
                        f"(`twinrl data repair {path}` rewrites it)"
                    )
    elif path.is_dir() and (path / "meta" / "info.json").is_file():
        from twinrl_data.lerobot_io import verify_dataset  # loads lerobot: only when asked

        result.checked, result.problems = verify_dataset(path)
    else:
        raise DataError(
            f"{path} is not a session folder, an episode .mcap file or a LeRobot dataset folder"
        )
    return result
