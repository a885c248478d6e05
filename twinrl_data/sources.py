"""One opener for every place episodes live.

A *source* is an episode ``.mcap`` file, a session folder, a LeRobotDataset folder or a
catalog ``.parquet`` (optionally filtered). Every command that reads episodes opens
them here, so each accepts the same sources and says the same thing about a wrong one.

- :func:`open_episodes`: the episodes of one source, lazily, and how many there are;
- :func:`open_episode`: one episode, ``PATH`` or ``PATH#N`` (the N-th of a session or
  dataset);
- :func:`discover_episodes`: every episode found under some paths (folders searched
  for sessions and datasets), as the catalog indexes them.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path

from twinrl_data import catalog
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import iter_dataset_episodes
from twinrl_data.live_export import LiveRows, read_for_export
from twinrl_data.mcap_log import read_episode
from twinrl_data.schema import Episode
from twinrl_data.session import Session, is_session
from twinrl_data.streams import read_live_episode

KINDS = "a session folder, an .mcap episode, a LeRobot dataset folder or a catalog .parquet"


def is_dataset(path: Path) -> bool:
    return (path / "meta" / "info.json").is_file()


def open_episodes(
    source: str | Path, *, where: str | None = None, images: bool = True, live: bool = False
) -> tuple[Iterator[Episode | LiveRows], int]:
    """The episodes of ``source`` in order, read as they are consumed, and their count.

    ``where`` is an SQL filter over a catalog's columns (catalogs only); ``images=False``
    skips decoding camera frames; ``live``: live episode files as their rows at their
    cameras' rate (:mod:`twinrl_data.live_export`, for export).
    """
    path = Path(source)
    if path.suffix == ".parquet":
        table = catalog.query(path, where=where)
        return catalog.load_selected(table, live=live), table.num_rows
    if where is not None:
        raise DataError(f"a filter selects rows of a catalog (.parquet); {path} is not one")

    def read(file: Path) -> Episode | LiveRows:
        return read_for_export(file) if live else read_episode(file, images=images)

    if path.suffix == ".mcap":
        return iter([read(path)]), 1
    if is_session(path):
        paths = _session_paths(path)
        return (read(p) for p in paths), len(paths)
    if is_dataset(path):
        count = int(json.loads((path / "meta" / "info.json").read_text())["total_episodes"])
        return iter_dataset_episodes(path, cameras=None if images else []), count
    raise DataError(f"{path} is not {KINDS}")


def _session_paths(path: Path) -> list[Path]:
    """The finished episodes of a session, saying (as warnings) what else it holds."""
    session = Session(path)
    session.warn()
    return session.readable_paths()


def open_episode(spec: str | Path, default_index: int = 0) -> Episode:
    """One episode: ``PATH`` (an .mcap file, or episode ``default_index`` of a session or
    dataset) or ``PATH#N`` (episode N)."""
    path_text, _, index_text = str(spec).partition("#")
    path = Path(path_text)
    if not index_text.isdigit() and index_text:
        raise DataError(f"{spec}: the part after '#' must be an episode number")
    index = int(index_text) if index_text else default_index
    if path.suffix == ".mcap":
        return read_episode(path)
    if is_session(path):
        paths = _session_paths(path)
        if not 0 <= index < len(paths):
            raise DataError(f"{path} has {len(paths)} episodes; episode {index} is out of range")
        return read_episode(paths[index])
    if is_dataset(path):
        return next(iter(iter_dataset_episodes(path, episodes=[index])))
    raise DataError(f"{path} is not an .mcap episode, a session or a LeRobot dataset")


def discover_episodes(
    paths: Iterable[str | Path], *, images: bool = False, samples: bool = False
) -> list[Episode]:
    """Every episode of the sessions, .mcap files and LeRobotDatasets found under
    ``paths`` (folders are searched as the catalog searches them); ``samples``: with
    live episodes' sample streams (a dataset has none)."""
    mcaps, datasets = catalog.discover(paths)
    read = read_live_episode if samples else read_episode
    episodes = [read(p, images=images) for p in mcaps]
    for root in datasets:
        episodes += list(iter_dataset_episodes(root, cameras=None if images else []))
    if not episodes:
        raise DataError("no episodes found in the given paths")
    return episodes
