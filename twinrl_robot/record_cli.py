"""``twinrl record``: record episodes with a person at a teleop device."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from twinrl_robot.cli import CellOption, EmulatedOption, PlantEffects
from twinrl_sim.tasks import TASKS

console = Console(soft_wrap=True)


def _status_line(status) -> str:
    gb = status.disk_free / 2**30
    kept = f"{status.saved} kept" + (f", {status.discarded} discarded" if status.discarded else "")
    last = f" | last: {status.last}" if status.last else ""
    return (
        f"episode {status.episode}/{status.episodes} | {status.state} | {status.elapsed:5.1f} s | "
        f"{status.frames} frames | {status.dropped} dropped | {gb:.1f} GiB free | {kept}{last}\n"
        "[dim]Enter start  s success  f failure  d discard  n note  q stop[/dim]"
    )


def record(
    out: Annotated[
        Path, typer.Option(help="Session folder (created, or continued when it exists).")
    ],
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")] = "pick_place",
    robot: Annotated[str, typer.Option(help="plant, or ur (with --cell).")] = "plant",
    cell: CellOption = None,
    emulated: EmulatedOption = False,
    teleop: Annotated[
        str,
        typer.Option(
            help="spacemouse, gamepad (or gamepad:/dev/input/eventN; gamepad:sdl for SDL's "
            "controller layout), keyboard, or scripted "
            "(the task's expert at a virtual device: plant and emulator only)."
        ),
    ] = "spacemouse",
    episodes: Annotated[
        int, typer.Option(help="Episodes to keep (discarded ones are redone).", min=1)
    ] = 10,
    plan: Annotated[
        str | None,
        typer.Option(
            help="Where episodes start: ID or OOD (sampled), a targets.json from 'twinrl mine', "
            "or a JSON list of configurations. Default: ID."
        ),
    ] = None,
    viewer: Annotated[bool, typer.Option(help="Spawn a Rerun viewer with the live view.")] = False,
    connect: Annotated[
        str | None, typer.Option(help="Send the live view to a running Rerun viewer at this URL.")
    ] = None,
    save_view: Annotated[
        Path | None, typer.Option(help="Save the live view to this .rrd file.")
    ] = None,
    keys: Annotated[
        bool, typer.Option(help="Read the marks' keys from the terminal (when it is one).")
    ] = True,
    effects: PlantEffects = None,
    settle: Annotated[
        int,
        typer.Option(
            help="Steps recorded after a success mark with the arm held still, so the last "
            "frames show the success (what 'twinrl train reward-classifier' learns from).",
            min=0,
        ),
    ] = 3,
    max_steps: Annotated[
        int | None,
        typer.Option(
            help="Steps before an episode ends as a failure (default: the task's).", min=1
        ),
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of sampled configurations.")] = 0,
) -> None:
    """Record episodes with a person at a teleop device: reset guidance, live view, marks.

    Each episode: set the cell up as the live view shows, press Enter (or the device's
    start button), drive, then s (success), f (failure) or d (discard and record again);
    n types a note, q stops. Every episode is on disk as it is recorded; run the same
    command again to continue a session (a crash's partial episode is recovered first).
    """
    from twinrl_data.errors import UsageError
    from twinrl_robot.recording import run_recording

    targets = [t for t in (viewer and "spawn", connect, save_view and str(save_view)) if t]
    if len(targets) > 1:
        raise UsageError("give one of --viewer, --connect and --save-view")
    if save_view is not None and save_view.suffix != ".rrd":
        raise UsageError(f"--save-view must name a .rrd file, got {save_view}")
    with Live(console=console, auto_refresh=False, transient=True) as live:
        report = run_recording(
            task,
            out,
            robot=robot,
            teleop=teleop,
            episodes=episodes,
            plan=plan,
            cell=cell,
            emulated=emulated,
            effects=effects,
            view=targets[0] if targets else None,
            keys=keys,
            seed=seed,
            max_steps=max_steps,
            settle=settle,
            on_status=lambda status: live.update(
                Text.from_markup(_status_line(status)), refresh=True
            ),
        )
    table = Table("episode", "outcome", "steps", "note", title=f"recorded into {out}")
    for episode in report.episodes:
        table.add_row(
            Path(episode.path).name, episode.outcome, str(episode.steps), episode.note or ""
        )
    console.print(table)
    if report.recovered:
        console.print(f"recovered first: {', '.join(Path(p).name for p in report.recovered)}")
    if report.discarded:
        console.print(f"discarded (kept in {out}/discarded): {len(report.discarded)}")
    console.print(
        f"inspect: twinrl view {out}  |  for learning: twinrl data export {out} --to DATASET"
    )
