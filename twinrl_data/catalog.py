"""The catalog: one Parquet table of episode metadata over any number of logs, in DuckDB.

Rows come from MCAP sessions (or single episode files) and LeRobot datasets. Columns:
the episode metadata (``task``, ``source``, ``world``, ``region``, ``twin``, ``policy``,
``success``, ``num_interventions``, ``fps``, ``robot``, ``created_at``, ``operator``,
``episode_id``, ``instruction``, ``aborted``: why it ended early, or null), where it
lives (``kind`` = ``mcap`` | ``lerobot``, ``path``, ``dataset_index``, ``episode_key``),
derived columns (``length`` in steps, ``duration_s``, ``return``, ``cameras``) and the
configuration, as JSON (``config``) and flattened (``config_object_0``,
``config_object_1``, ... for list values).

Curation is a query: select rows, then export exactly those episodes as a dataset.
"""

from __future__ import annotations

import difflib
import json
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from mcap.reader import make_reader

from twinrl_data import schema as contract
from twinrl_data.atomic import write_atomic
from twinrl_data.errors import DataError, SettingError
from twinrl_data.lerobot_io import (
    episode_metadata,
    iter_dataset_episodes,
    open_dataset,
    read_sidecar,
)
from twinrl_data.live_export import LiveRows, read_for_export
from twinrl_data.mcap_log import CAMERA_PREFIX, read_episode
from twinrl_data.session import Session, is_session

DEFAULT_CATALOG = Path("catalog.parquet")
META_COLUMNS = (
    "episode_id",
    "task",
    "instruction",
    "source",
    "world",
    "region",
    "twin",
    "policy",
    "success",
    "num_interventions",
    "fps",
    "robot",
    "created_at",
    "operator",
    "aborted",
    "note",
)
FILTERS = ("task", "source", "world", "region")


def flatten_config(config: dict[str, Any]) -> dict[str, Any]:
    """``{"object": [x, y, yaw]}`` -> ``{"config_object_0": x, ...}``; scalars keep their key."""
    flat = {}
    for key, value in config.items():
        name = re.sub(r"\W", "_", str(key))
        if isinstance(value, list | tuple):
            for i, item in enumerate(value):
                if isinstance(item, int | float | bool):
                    flat[f"config_{name}_{i}"] = float(item)
        elif isinstance(value, int | float | bool):
            flat[f"config_{name}"] = float(value)
    return flat


def _row(
    meta: contract.EpisodeMeta,
    *,
    kind: str,
    path: Path,
    index: int | None,
    length: int,
    total_reward: float | None,
    cameras: list[str],
) -> dict[str, Any]:
    row: dict[str, Any] = {name: getattr(meta, name) for name in META_COLUMNS}
    row.update(
        episode_key=f"{kind}:{path.resolve()}" + (f"#{index}" if index is not None else ""),
        kind=kind,
        path=str(path.resolve()),
        dataset_index=index,
        length=length,
        duration_s=length / meta.fps,
        cameras=",".join(cameras),
        config=json.dumps(meta.config),
    )
    row["return"] = total_reward
    row.update(flatten_config(meta.config))
    return row


def _mcap_rows(paths: Iterable[Path]) -> Iterator[dict[str, Any]]:
    for path in paths:
        episode = read_episode(path, images=False)
        reward = episode.data.get(contract.REWARD)
        yield _row(
            episode.meta,
            kind="mcap",
            path=path,
            index=None,
            length=len(episode),
            total_reward=None if reward is None else float(reward.sum()),
            cameras=_cameras_in(path),
        )


def _cameras_in(path: Path) -> list[str]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None:
        return []
    return sorted(
        c.topic[len(CAMERA_PREFIX) :]
        for c in summary.channels.values()
        if c.topic.startswith(CAMERA_PREFIX)
    )


def _lerobot_rows(root: Path) -> Iterator[dict[str, Any]]:
    dataset = open_dataset(root)
    meta = dataset.meta
    sidecar = read_sidecar(root)
    table = dataset.hf_dataset.with_format("numpy")
    episode_column = np.asarray(table["episode_index"])
    rewards = (
        np.asarray(table[contract.REWARD]).reshape(-1) if contract.REWARD in meta.features else None
    )
    success = (
        np.asarray(table[contract.SUCCESS]).reshape(-1)
        if contract.SUCCESS in meta.features
        else None
    )
    cameras = [k.removeprefix(contract.IMAGES_PREFIX) for k in meta.video_keys]
    task_column = np.asarray(table["task_index"])
    for index in range(meta.total_episodes):
        rows = episode_column == index
        episode_meta = episode_metadata(
            meta, sidecar, index, int(task_column[rows][0]), source="teleop", world="real"
        )
        if index not in sidecar and success is not None:
            episode_meta = episode_meta.replace(success=bool(success[rows][-1]))
        yield _row(
            episode_meta,
            kind="lerobot",
            path=root,
            index=index,
            length=int(rows.sum()),
            total_reward=None if rewards is None else float(rewards[rows].sum()),
            cameras=cameras,
        )


def discover(paths: Iterable[str | Path]) -> tuple[list[Path], list[Path]]:
    """Episode MCAP files and LeRobot dataset roots found under ``paths``."""
    mcaps: list[Path] = []
    datasets: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise DataError(
                f"{path} does not exist; give session folders, .mcap files or LeRobot datasets"
            )
        if path.is_file():
            if path.suffix != ".mcap":
                raise DataError(f"{path} is neither an .mcap episode nor a folder")
            mcaps.append(path)
        elif is_session(path):
            session = Session(path)
            session.warn()
            mcaps.extend(session.readable_paths())
        elif (path / "meta" / "info.json").is_file():
            datasets.append(path)
        else:
            found = sorted(path.rglob("manifest.json")) + sorted(path.rglob("meta/info.json"))
            if not found:
                raise DataError(
                    f"{path} holds no session (manifest.json) "
                    "and no LeRobot dataset (meta/info.json)"
                )
            inner_mcaps, inner_datasets = discover(
                [p.parent if p.name == "manifest.json" else p.parent.parent for p in found]
            )
            mcaps.extend(inner_mcaps)
            datasets.extend(inner_datasets)
    return sorted(set(mcaps)), sorted(set(datasets))


@dataclass(frozen=True)
class IndexReport:
    catalog: Path
    indexed: int
    total: int


def build_index(paths: Iterable[str | Path], catalog: str | Path = DEFAULT_CATALOG) -> IndexReport:
    """Add (or refresh) every episode under ``paths`` in the catalog Parquet file."""
    catalog = Path(catalog)
    mcaps, datasets = discover(paths)
    rows = list(_mcap_rows(mcaps))
    for root in datasets:
        rows.extend(_lerobot_rows(root))
    new = pa.Table.from_pylist(rows) if rows else None
    old = _read(catalog) if catalog.exists() else None
    if old is not None and new is not None:
        keep = ~np.isin(np.asarray(old["episode_key"]), np.asarray(new["episode_key"]))
        old = old.filter(pa.array(keep))
        table = pa.concat_tables([old, new], promote_options="permissive")
    else:
        table = new if new is not None else old
    if table is None:
        raise DataError("no episodes found to index")
    _write(table, catalog)
    return IndexReport(catalog=catalog, indexed=len(rows), total=table.num_rows)


def _read(catalog: Path) -> pa.Table:
    try:
        return pq.read_table(catalog)
    except Exception as err:
        raise DataError(
            f"{catalog} is not a readable catalog ({err}); rebuild it with `twinrl data index`"
        ) from None


def _write(table: pa.Table, catalog: Path) -> None:
    """Replace the catalog whole (fsynced, permissions from the umask)."""
    catalog.parent.mkdir(parents=True, exist_ok=True)
    buffer = pa.BufferOutputStream()
    pq.write_table(table, buffer)
    write_atomic(catalog, buffer.getvalue().to_pybytes())


def open_catalog(catalog: str | Path = DEFAULT_CATALOG) -> duckdb.DuckDBPyConnection:
    """A DuckDB connection with the catalog as the view ``episodes``."""
    catalog = Path(catalog)
    if not catalog.is_file():
        raise DataError(
            f"catalog {catalog} does not exist; build it first by indexing the sessions "
            "(twinrl data index)"
        )
    _read(catalog)
    con = duckdb.connect()
    con.execute(f"CREATE VIEW episodes AS SELECT * FROM read_parquet('{_sql_string(catalog)}')")
    return con


def _sql_string(path: Path) -> str:
    return str(path.resolve()).replace("'", "''")


def query(
    catalog: str | Path = DEFAULT_CATALOG,
    *,
    task: str | None = None,
    source: str | None = None,
    world: str | None = None,
    region: str | None = None,
    success: bool | None = None,
    where: str | None = None,
    sql: str | None = None,
    columns: Iterable[str] | None = None,
    limit: int | None = None,
    aborted: bool | None = None,
) -> pa.Table:
    """Rows of the catalog matching every given filter (or the result of free ``sql``
    over the view ``episodes``); ``aborted`` keeps only episodes that ended early (True)
    or only those that ran their course (False). Unknown columns get an error naming the
    nearest one."""
    con = open_catalog(catalog)
    available = [row[0] for row in con.execute("DESCRIBE episodes").fetchall()]
    if sql is not None:
        if any(v is not None for v in (task, source, world, region, success, where, aborted)):
            raise SettingError("sql", "is a whole query; combine it with no other filter")
        return _run(con, sql, [], available)
    clauses, params = [], []
    for name, value in (("task", task), ("source", source), ("world", world), ("region", region)):
        if value is not None:
            clauses.append(f'"{name}" = ?')
            params.append(value)
    if success is not None:
        clauses.append("success = ?")
        params.append(success)
    if aborted is not None and "aborted" in available:  # catalogs older than the column
        clauses.append("aborted IS NOT NULL" if aborted else "aborted IS NULL")
    if where:
        clauses.append(f"({where})")
    selected = "*"
    if columns:
        wanted = list(columns)
        for name in wanted:
            _check_column(name, available)
        selected = ", ".join(f'"{c}"' for c in wanted)
    statement = f"SELECT {selected} FROM episodes"
    if clauses:
        statement += " WHERE " + " AND ".join(clauses)
    statement += " ORDER BY created_at, episode_key"
    if limit is not None:
        statement += f" LIMIT {int(limit)}"
    return _run(con, statement, params, available)


def _check_column(name: str, available: list[str]) -> None:
    if name not in available:
        close = difflib.get_close_matches(name, available, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise DataError(f"unknown catalog column '{name}'{hint}; columns: {', '.join(available)}")


def _run(
    con: duckdb.DuckDBPyConnection, statement: str, params: list[Any], available: list[str]
) -> pa.Table:
    try:
        return con.sql(statement, params=params).to_arrow_table()
    except duckdb.Error as err:
        message = str(err).splitlines()[0]
        column = re.search(r'column "?([\w.]+)"? not found', message, flags=re.I)
        if column:
            _check_column(column.group(1), available)
        raise DataError(f"query failed: {message}") from None


def load_selected(table: pa.Table, *, live: bool = False) -> Iterator[contract.Episode | LiveRows]:
    """The episodes behind catalog rows (as selected by :func:`query`), in row order;
    ``live``: live episode files as their rows at their cameras' rate (for export)."""
    rows = table.select(["kind", "path", "dataset_index"]).to_pylist() if table.num_rows else []
    for row in rows:
        if row["kind"] == "mcap":
            yield read_for_export(row["path"]) if live else read_episode(row["path"])
        else:
            yield next(iter_dataset_episodes(row["path"], episodes=[int(row["dataset_index"])]))
