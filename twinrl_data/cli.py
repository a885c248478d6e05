"""``twinrl data``: recover, export, import, index, query and curate episode logs."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from twinrl_data import catalog as catalog_lib
from twinrl_data import schema as contract
from twinrl_data.console import progress, quiet_encoders
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import (
    export_dataset,
    iter_dataset_episodes,
    missing_contract_fields,
    open_dataset,
)
from twinrl_data.live_export import LiveRows
from twinrl_data.repair import repair_session, verify
from twinrl_data.salvage import recover
from twinrl_data.session import Session
from twinrl_data.settings_cli import name_flags
from twinrl_data.sources import open_episodes

name_flags(output="--out")

app = typer.Typer(
    help="Episode logs: recover MCAP, export/import LeRobot datasets, catalog.",
    no_args_is_help=True,
)
console = Console(soft_wrap=True)  # paths and figures are never broken across lines
CatalogOption = Annotated[Path, typer.Option("--catalog", help="Catalog Parquet file.")]
DEFAULT_COLUMNS = (
    "episode_id",
    "task",
    "source",
    "world",
    "region",
    "success",
    "length",
    "return",
    "kind",
)


def export_with_progress(
    episodes: Iterator[contract.Episode | LiveRows],
    count: int,
    to: Path,
    *,
    repo_id: str | None,
    force: bool,
) -> None:
    """Export with a progress bar and a one-line summary."""
    quiet_encoders()
    with progress() as bar:
        job = bar.add_task(f"export to {to}", total=count)
        result = export_dataset(
            episodes, to, repo_id=repo_id, force=force, on_episode=lambda _: bar.advance(job)
        )
    console.print(
        f"{result.root}: {result.episodes} episodes, {result.frames} frames "
        f"(repo id {result.repo_id})"
    )


@app.command("recover")
def recover_command(
    file: Annotated[Path, typer.Argument(help="Truncated or damaged episode .mcap file.")],
    out: Annotated[
        Path | None, typer.Option(help="Where to write (default: FILE.recovered.mcap).")
    ] = None,
    force: Annotated[bool, typer.Option(help="Overwrite --out if it exists.")] = False,
) -> None:
    """Rewrite what is intact of an episode log (a killed recorder's, or one with a
    damaged chunk) into a new, valid file."""
    if file.is_dir():
        raise DataError(
            f"{file} is a folder; give one episode .mcap file (`twinrl data repair {file}` "
            "recovers every unfinished episode of a session)"
        )
    result = recover(file, out, force=force)
    if result.complete:
        state = "the file was complete"
    elif result.lost_spans:
        seconds = sum(end - start for start, end in result.lost_spans) / 1e9
        state = f"{len(result.lost_spans)} damaged chunks ({seconds:.1f} s of log) left out"
    else:
        state = "the file was truncated"
    console.print(
        f"{result.output}: kept {result.messages} messages and "
        f"{result.metadata} metadata records ({state})"
    )


@app.command("repair")
def repair_command(
    session: Annotated[Path, typer.Argument(help="Session folder.")],
) -> None:
    """Rebuild a session's manifest from its episode files: adopt files it lacks, report
    files it lists that are gone, recover unfinished or damaged episodes (originals kept
    under damaged/). Nothing is deleted."""
    report = repair_session(session)
    console.print(
        f"{session}: {report.episodes} episodes listed (manifest was {report.manifest_was}); "
        f"adopted {len(report.adopted)}, recovered {len(report.recovered)}, "
        f"missing {len(report.missing)}, empty {len(report.empty)}, "
        f"unreadable {len(report.unreadable)}"
    )
    for line in report.missing:
        console.print(f"  missing: {line}")
    for line in report.unreadable:
        console.print(f"  unreadable: {line}")
    for line in report.busy:
        console.print(f"  still being recorded, left alone: {line}")


@app.command("verify")
def verify_command(
    path: Annotated[
        Path, typer.Argument(help="Session folder, episode .mcap file or LeRobot dataset folder.")
    ],
) -> None:
    """Check every file the way `git fsck` does: checksums, decodable messages and
    frames, the manifest against the files, a dataset's metadata against its data. Exits
    with status 1 when anything is wrong."""
    result = verify(path)
    for problem in result.problems:
        console.print(f"[red]problem:[/red] {problem}", highlight=False)
    console.print(f"{path}: {result.checked} files checked, {len(result.problems)} problems")
    if result.problems:
        raise typer.Exit(1)


@app.command("export")
def export_command(
    source: Annotated[
        Path, typer.Argument(help="Session folder, episode .mcap, or catalog .parquet.")
    ],
    to: Annotated[Path, typer.Option(help="LeRobotDataset folder to create.")],
    repo_id: Annotated[
        str | None, typer.Option(help="Dataset repo id (default: twinrl/<folder>).")
    ] = None,
    where: Annotated[
        str | None, typer.Option(help="SQL filter over the catalog's columns.")
    ] = None,
    force: Annotated[bool, typer.Option(help="Replace --to if it exists.")] = False,
) -> None:
    """Write episodes as a LeRobotDataset v3 (videos for cameras, metadata preserved); a
    live episode (a real cell's) at its cameras' rate, a dataset frame a camera period."""
    if where is not None and source.suffix != ".parquet":
        raise DataError("--where filters a catalog; give a catalog .parquet as SOURCE")
    episodes, count = open_episodes(source, where=where, live=True)
    export_with_progress(episodes, count, to, repo_id=repo_id, force=force)


@app.command("import")
def import_command(
    dataset: Annotated[
        Path, typer.Argument(help="LeRobotDataset folder (twinrl's or lerobot's own).")
    ],
    to: Annotated[Path, typer.Option(help="Session folder to create with the episodes.")],
    source: Annotated[
        str,
        typer.Option(
            help=f"Source of episodes without twinrl metadata: {', '.join(contract.SOURCES)}."
        ),
    ] = "teleop",
    world: Annotated[
        str,
        typer.Option(
            help=f"World of episodes without twinrl metadata: {', '.join(contract.WORLDS)}."
        ),
    ] = "real",
) -> None:
    """Turn a LeRobotDataset into episode logs; report the contract fields it lacks."""
    opened = open_dataset(dataset)
    missing = missing_contract_fields(opened.meta.features)
    session = Session.create(to)
    total = opened.meta.total_episodes
    with progress() as bar:
        job = bar.add_task(f"import {dataset.name}", total=total)
        for episode in iter_dataset_episodes(dataset, source=source, world=world):
            session.add(episode)
            bar.advance(job)
    console.print(f"{to}: {total} episodes imported")
    if missing:
        console.print(
            f"[yellow]the dataset lacks {', '.join(missing)}; "
            "those fields are absent in the episodes[/yellow]"
        )


@app.command("index")
def index_command(
    paths: Annotated[
        list[Path],
        typer.Argument(help="Sessions, .mcap files, LeRobot datasets, or folders of them."),
    ],
    catalog: CatalogOption = catalog_lib.DEFAULT_CATALOG,
) -> None:
    """Build or refresh the catalog of every episode found under PATHS."""
    report = catalog_lib.build_index(paths, catalog)
    console.print(
        f"{report.catalog}: indexed {report.indexed} episodes, {report.total} in the catalog"
    )


def _print_table(table, as_json: bool) -> None:
    rows = table.to_pylist()
    if as_json:
        print(json.dumps(rows, default=str))
        return
    view = Table(title=f"{len(rows)} rows")
    for name in table.column_names:
        view.add_column(name, overflow="fold")
    for row in rows:
        view.add_row(*[_cell(v) for v in row.values()])
    console.print(view)


def _cell(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.3g}"
    return "" if value is None else str(value)


@app.command("query")
def query_command(
    catalog: CatalogOption = catalog_lib.DEFAULT_CATALOG,
    task: Annotated[str | None, typer.Option(help="Only this task.")] = None,
    source: Annotated[
        str | None, typer.Option(help="Only this source (teleop, twin_demo, ...).")
    ] = None,
    world: Annotated[str | None, typer.Option(help="Only this world (real, twin, plant).")] = None,
    region: Annotated[str | None, typer.Option(help="Only this region (ID, OOD).")] = None,
    success: Annotated[
        bool | None, typer.Option("--success/--failure", help="Only successes or failures.")
    ] = None,
    where: Annotated[
        str | None, typer.Option(help='Extra SQL condition, e.g. "length > 50".')
    ] = None,
    sql: Annotated[
        str | None, typer.Option(help="A whole SQL query over the view `episodes`.")
    ] = None,
    columns: Annotated[str | None, typer.Option(help="Comma-separated columns to show.")] = None,
    limit: Annotated[int | None, typer.Option(help="At most this many rows.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the rows as JSON.")] = False,
) -> None:
    """Select episodes from the catalog (filters are combined with AND)."""
    chosen = (
        [c.strip() for c in columns.split(",")]
        if columns
        else (None if as_json or sql else DEFAULT_COLUMNS)
    )
    table = catalog_lib.query(
        catalog,
        task=task,
        source=source,
        world=world,
        region=region,
        success=success,
        where=where,
        sql=sql,
        columns=chosen,
        limit=limit,
    )
    _print_table(table, as_json)


@app.command("curate")
def curate_command(
    to: Annotated[Path, typer.Option(help="LeRobotDataset folder to create.")],
    catalog: CatalogOption = catalog_lib.DEFAULT_CATALOG,
    task: Annotated[str | None, typer.Option(help="Only this task.")] = None,
    source: Annotated[str | None, typer.Option(help="Only this source.")] = None,
    world: Annotated[str | None, typer.Option(help="Only this world.")] = None,
    region: Annotated[str | None, typer.Option(help="Only this region.")] = None,
    success: Annotated[
        bool | None, typer.Option("--success/--failure", help="Only successes or failures.")
    ] = None,
    where: Annotated[str | None, typer.Option(help="Extra SQL condition.")] = None,
    repo_id: Annotated[str | None, typer.Option(help="Dataset repo id.")] = None,
    force: Annotated[bool, typer.Option(help="Replace --to if it exists.")] = False,
    keep_aborted: Annotated[
        bool,
        typer.Option(
            help="Also export episodes that ended early (a stop, a lost connection): they "
            "are partial, so they are left out unless asked for."
        ),
    ] = False,
) -> None:
    """Export exactly the selected catalog episodes as a new LeRobotDataset (live
    episodes at their cameras' rate)."""
    filters = dict(task=task, source=source, world=world, region=region, success=success)
    table = catalog_lib.query(
        catalog, **filters, where=where, aborted=None if keep_aborted else False
    )
    if not keep_aborted:
        partial = catalog_lib.query(catalog, **filters, where=where, aborted=True).num_rows
        if partial:
            console.print(
                f"left out {partial} episode(s) that ended early; --keep-aborted exports them"
            )
    if table.num_rows == 0:
        raise DataError(
            "the selection is empty; loosen the filters (try `twinrl data query` first)"
        )
    export_with_progress(
        catalog_lib.load_selected(table, live=True),
        table.num_rows,
        to,
        repo_id=repo_id,
        force=force,
    )
