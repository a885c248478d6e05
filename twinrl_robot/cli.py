"""Commands that act in a world (twin or plant): the scripted expert for now."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from twinrl_data.console import progress
from twinrl_data.errors import UsageError
from twinrl_data.session import Session
from twinrl_robot.backends import WORLDS
from twinrl_robot.excitation import ExcitationSettings, run_excitation
from twinrl_robot.plant import DEFAULT_EFFECTS_FILE
from twinrl_robot.scripted import ExpertReport, run_scripted_expert
from twinrl_sim.tasks import REGION_NAMES, TASKS, task_class, task_on_twin

console = Console(soft_wrap=True)  # paths and figures are never broken across lines
PlantEffects = Annotated[
    Path | None,
    typer.Option(help=f"Hidden effects YAML for the plant (default: {DEFAULT_EFFECTS_FILE.name})."),
]
CellOption = Annotated[
    Path | None,
    typer.Option(help="Cell file of the real arm (--world real), see 'twinrl cell check'."),
]
EmulatedOption = Annotated[
    bool,
    typer.Option(
        help="The --cell is served by 'twinrl robot emulate': it sets each configuration up "
        "and lends the plant's ground truth (object poses, success), which a real cell lacks."
    ),
]


def check_real(worlds: list[str], cell: Path | None, emulated: bool) -> None:
    """--world real needs --cell; --cell and --emulated need --world real."""
    if "real" in worlds and cell is None:
        raise UsageError("--world real needs the arm's --cell file")
    if (cell is not None or emulated) and "real" not in worlds:
        raise UsageError("--cell and --emulated describe a real arm; add --world real")


def expert(
    task: Annotated[str, typer.Argument(help=f"Task ({', '.join(TASKS)}) or 'all'.")],
    episodes: Annotated[int, typer.Option(help="Episodes per region.", min=1)] = 20,
    twin: Annotated[
        str | None,
        typer.Option(
            help="Scene spec YAML of the cell (e.g. from 'twinrl twin build'); it must hold "
            "the task's objects. Default: the task's built-in cell."
        ),
    ] = None,
    region: Annotated[str | None, typer.Option(help="Run only ID or OOD (default: both).")] = None,
    world: Annotated[
        list[str] | None, typer.Option(help=f"World: {' or '.join(WORLDS)}; repeat for both.")
    ] = None,
    effects: PlantEffects = None,
    seed: Annotated[int, typer.Option(help="Seed for configurations and grasps.")] = 0,
    noise: Annotated[
        float,
        typer.Option(
            help="Operator-like jitter the expert corrects: m per step (rotations: 5x, in "
            "rad), e.g. 0.002 for teleop-like demos.",
            min=0.0,
        ),
    ] = 0.0,
    out: Annotated[
        Path | None,
        typer.Option(help="Record every episode (MCAP, both cameras) into this session folder."),
    ] = None,
    append: Annotated[bool, typer.Option(help="Add to an existing --out session.")] = False,
    settle: Annotated[
        int,
        typer.Option(
            help="Steps recorded after a success with the arm held, so the last frames show "
            "the success (what 'twinrl train reward-classifier' learns from), e.g. 3.",
            min=0,
        ),
    ] = 0,
    near_misses: Annotated[
        float,
        typer.Option(
            help="Share of the episodes in which the expert stops short near the goal and "
            "holds (an object held over its goal, a peg above its hole, a board wiped in "
            "part): the hard negatives a reward classifier learns from, e.g. 0.3.",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object per task and world.")
    ] = False,
    cell: CellOption = None,
    emulated: EmulatedOption = False,
) -> None:
    """Run a task's scripted expert, report its success per region, optionally record it."""
    worlds = world or ["twin"]
    tasks = list(TASKS) if task == "all" else [task_class(task).name]
    if region is not None and region not in REGION_NAMES:
        raise UsageError(f"--region must be one of {', '.join(REGION_NAMES)}, got '{region}'")
    unknown = [w for w in worlds if w not in WORLDS]
    if unknown:
        raise UsageError(f"--world must be one of {', '.join(WORLDS)}, got '{unknown[0]}'")
    if effects is not None and "plant" not in worlds:
        raise UsageError("--effects applies to --world plant only")
    if effects is not None and not effects.is_file():
        raise UsageError(f"--effects {effects} does not exist")
    check_real(worlds, cell, emulated)
    regions = (region,) if region else REGION_NAMES
    scene = None
    if twin is not None:
        if len(tasks) != 1:
            raise UsageError("--twin is the cell of one task; name the task instead of 'all'")
        scene = task_on_twin(tasks[0], twin)
    session = Session.create(out, exist_ok=append) if out is not None else None
    reports: list[ExpertReport] = []
    with progress(disable=as_json) as bar:
        for name in tasks:
            for place in worlds:
                job = bar.add_task(f"{name} in the {place}", total=episodes * len(regions))
                report = run_scripted_expert(
                    name,
                    world=place,  # type: ignore[arg-type]
                    episodes=episodes,
                    regions=regions,
                    effects=effects if place == "plant" else None,
                    seed=seed,
                    session=session,
                    action_noise=noise,
                    on_episode=lambda _, job=job: bar.advance(job),
                    scene=scene,
                    cell=cell if place == "real" else None,
                    emulated=emulated and place == "real",
                    settle=settle,
                    near_misses=near_misses,
                )
                reports.append(report)
                if as_json:
                    print(json.dumps(report.to_json()), flush=True)
    if not as_json:
        console.print(success_table(reports))
        if session is not None:
            recorded = sum(len(r.episodes) for r in reports)
            session.refresh()
            console.print(
                f"recorded {recorded} episodes in {session.path} "
                f"({len(session.entries)} in the session)"
            )


def success_table(reports: list[ExpertReport]) -> Table:
    """One row per task and world, one column per region."""
    regions = [r for r in REGION_NAMES if any(r in rep.success_rate() for rep in reports)]
    table = Table(
        "task", "world", *[f"{r} success" for r in regions], "episodes", title="scripted expert"
    )
    for report in reports:
        rates = report.success_rate()
        cells = [f"{100 * rates[r]:.0f} %" if r in rates else "-" for r in regions]
        table.add_row(report.task, report.world, *cells, str(len(report.episodes)))
    return table


def excite(
    out: Annotated[Path, typer.Option(help="Session folder to create with the episodes.")],
    task: Annotated[
        str, typer.Option(help=f"Task whose cell and object placement to use: {', '.join(TASKS)}.")
    ] = "pick_place",
    twin: Annotated[
        str | None,
        typer.Option(
            help="Scene spec YAML of the cell (e.g. with your robot's MJCF); it must hold "
            "the task's objects. Default: the task's built-in cell."
        ),
    ] = None,
    world: Annotated[str, typer.Option(help="twin, plant or real (with --cell).")] = "twin",
    episodes: Annotated[int, typer.Option(help="Episodes to record.", min=1)] = 4,
    effects: PlantEffects = None,
    duration: Annotated[float, typer.Option(help="Seconds per episode.")] = 10.0,
    amplitude: Annotated[
        float, typer.Option(help="Scale of the joint amplitudes (halved until safe).")
    ] = 1.0,
    seed: Annotated[int, typer.Option(help="Seed for phases and object placement.")] = 0,
    cell: CellOption = None,
    emulated: EmulatedOption = False,
) -> None:
    """Record safe multi-sine joint motions (source ``excitation``) for identification."""
    if world not in WORLDS:
        raise UsageError(f"--world must be {' or '.join(WORLDS)}, got '{world}'")
    check_real([world], cell, emulated)
    if effects is not None and not effects.is_file():
        raise UsageError(f"--effects {effects} does not exist")
    settings = ExcitationSettings(duration=duration, amplitude=amplitude)
    scene = task_on_twin(task, twin) if twin is not None else None
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"{out} exists and is not empty; choose another --out")
    session = Session.create(out)
    with progress() as bar:
        job = bar.add_task(f"excite {task} in the {world}", total=episodes)
        run_excitation(
            task,
            scene=scene,
            world=world,
            episodes=episodes,
            effects=effects,
            settings=settings,
            seed=seed,
            session=session,
            on_episode=lambda _: bar.advance(job),
            cell=cell,
            emulated=emulated,
        )
    console.print(f"{out}: {episodes} excitation episodes of {duration:g} s ({world})")


cell_app = typer.Typer(help="Real cells: their files (arm, gripper, cameras, safety).")


@cell_app.command("check")
def cell_check(
    file: Annotated[Path, typer.Argument(help="Cell file (YAML).", show_default=False)],
) -> None:
    """Validate a cell file and the twin it names; print what it describes."""
    from twinrl_robot.cell_file import load_cell
    from twinrl_robot.realtime import realtime_note
    from twinrl_sim.tasks import twin_scene

    cell = load_cell(file)
    scene = twin_scene(cell.twin)
    arm, safety = cell.arm, cell.safety
    table = Table(title=f"cell {cell.name}", show_header=False)
    table.add_row("arm", f"{arm.model} at {arm.host}")
    table.add_row("rates", f"control {arm.control_hz:g} Hz, {arm.servo} at {arm.servo_rate:g} Hz")
    if arm.realtime_priority is not None:
        table.add_row("real time", realtime_note(arm.realtime_priority))
    table.add_row("tcp offset", " ".join(f"{v:g}" for v in arm.tcp_offset))
    table.add_row("payload", f"{arm.payload.mass:g} kg")
    table.add_row("gripper", cell.gripper.kind)
    cameras = ", ".join(
        f"{c.name} ({c.kind} {c.width}x{c.height} @ {c.fps:g})" for c in cell.cameras
    )
    table.add_row("cameras", cameras or "none")
    table.add_row(
        "safety",
        f"box {list(safety.workspace.low)}..{list(safety.workspace.high)} m, tool cone "
        f"{safety.tool_cone_deg:g} deg, {safety.table_clearance:g} m above the table, "
        f"{safety.max_step_translation:g} m and "
        f"{safety.max_step_rotation:g} rad per step, joints {safety.max_joint_speed:g} rad/s, "
        f"watchdog {safety.watchdog_ms:g} ms",
    )
    table.add_row("twin", f"{scene.name} ({cell.twin})")
    console.print(table)
