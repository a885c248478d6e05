"""Commands that act in a world (twin or plant): the scripted expert for now."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from twinrl_robot.plant import DEFAULT_EFFECTS_FILE
from twinrl_robot.scripted import WORLDS, run_scripted_expert
from twinrl_sim.tasks import REGION_NAMES, TASKS

console = Console()


def expert(
    task: Annotated[str, typer.Argument(help=f"Task: {', '.join(TASKS)}.")],
    episodes: Annotated[int, typer.Option(help="Episodes per region.", min=1)] = 20,
    region: Annotated[str | None, typer.Option(help="Run only ID or OOD (default: both).")] = None,
    world: Annotated[str, typer.Option(help=f"World: {' or '.join(WORLDS)}.")] = "twin",
    effects: Annotated[
        Path | None,
        typer.Option(
            help=f"Hidden effects YAML for the plant (default: {DEFAULT_EFFECTS_FILE.name})."
        ),
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed for configurations and grasps.")] = 0,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object instead of a table.")
    ] = False,
) -> None:
    """Run TASK's scripted expert and report its success rate per region."""
    if region is not None and region not in REGION_NAMES:
        raise ValueError(f"--region must be one of {', '.join(REGION_NAMES)}, got '{region}'")
    if world not in WORLDS:
        raise ValueError(f"--world must be one of {', '.join(WORLDS)}, got '{world}'")
    if effects is not None and world != "plant":
        raise ValueError("--effects applies to --world plant only")
    if effects is not None and not effects.is_file():
        raise ValueError(f"--effects {effects} does not exist")
    regions = (region,) if region else REGION_NAMES
    with Progress(
        TextColumn(f"{task} in the {world}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        disable=as_json,
        transient=True,
    ) as bar:
        job = bar.add_task("episodes", total=episodes * len(regions))
        report = run_scripted_expert(
            task,
            world=world,  # type: ignore[arg-type]
            episodes=episodes,
            regions=regions,
            effects=effects,
            seed=seed,
            on_episode=lambda _: bar.advance(job),
        )
    if as_json:
        print(json.dumps(report.to_json()))
        return
    table = Table("task", "world", "region", "episodes", "success", title="scripted expert")
    counts = report.counts()
    for name, rate in report.success_rate().items():
        table.add_row(task, world, name, str(counts[name]), f"{100 * rate:.0f} %")
    console.print(table)
