"""``twinrl robot``: a real cell's arm: check it, or emulate its controller."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from twinrl_data.errors import UsageError
from twinrl_robot.cli import CellOption, EmulatedOption, PlantEffects

console = Console(soft_wrap=True)
robot_app = typer.Typer(help="A real cell's arm (UR over ur_rtde): check it, or emulate it.")
CellArgument = Annotated[Path, typer.Argument(help="Cell file (YAML).", show_default=False)]
TaskOption = Annotated[
    str | None,
    typer.Option(help="Task on the cell (default: the cell's twin, when it is a built-in cell)."),
]


def _cell_and_task(cell_file: Path, task: str | None):
    from twinrl_robot.cell_file import load_cell
    from twinrl_sim.tasks import make_task, task_on_twin

    cell = load_cell(cell_file)
    name = task or cell.twin
    return cell, make_task(name, task_on_twin(name, cell.twin))


@robot_app.command("emulate")
def emulate(
    cell_file: CellArgument,
    task: TaskOption = None,
    effects: PlantEffects = None,
) -> None:
    """Serve a UR controller's protocols for the cell on its (loopback) host, backed by the
    plant: RTDE, the script port, the dashboard, the Robotiq socket, the cameras. An
    emulator, not URSim. Ctrl-C stops it."""
    from twinrl_robot.plant import hidden_effects
    from twinrl_robot.ur.emulator.emulator import Emulator, serve

    cell, spec_task = _cell_and_task(cell_file, task)
    emulator = Emulator(cell, spec_task, effects=hidden_effects(effects), host=cell.arm.host)
    serve(emulator, lambda line: print(line, flush=True))


@robot_app.command("check")
def check(
    cell_file: CellArgument,
    task: TaskOption = None,
    seconds: Annotated[float, typer.Option(help="How long to measure.", min=0.5)] = 2.0,
    rerun: Annotated[
        Path | None,
        typer.Option(help="Write the safety box, the arm and the tool's path to this .rrd file."),
    ] = None,
) -> None:
    """Connect to the cell's arm, gripper and cameras and report what they measure."""
    from twinrl_robot.ur.check import check_cell

    cell, spec_task = _cell_and_task(cell_file, task)
    report = check_cell(cell, spec_task, seconds=seconds, rerun=rerun)
    table = Table(title=f"cell {cell.name} at {cell.arm.host}", show_header=False)
    table.add_row("controller", f"PolyScope {report.controller}")
    table.add_row("modes", f"robot {report.robot_mode}, safety {report.safety_mode}")
    table.add_row("remote control", "yes" if report.remote_control else "[red]no[/red]")
    p50, p99, worst = report.period_ms
    table.add_row(
        "servo loop",
        f"{report.servo_hz:g} Hz: period p50 {p50:.2f} ms, p99 {p99:.2f} ms, max {worst:.2f} ms",
    )
    table.add_row("gripper", f"{report.gripper}, opening {report.gripper_opening * 1000:.0f} mm")
    for camera in report.cameras:
        table.add_row(
            f"camera {camera.name}",
            f"{camera.fps:.1f} fps, frame age p50 {camera.age_ms_p50:.0f} ms, "
            f"{camera.dropped} dropped",
        )
    table.add_row("pose", report.pose_problem or "inside the safety limits")
    if report.recording is not None:
        table.add_row("recording", str(report.recording))
    console.print(table)
    if report.pose_problem:
        raise typer.Exit(1)


def replay(
    episode: Annotated[
        str, typer.Argument(help="Episode to replay: .mcap, session or dataset, each as PATH#N.")
    ],
    out: Annotated[
        Path, typer.Option(help="Session to record the replay into (created or added to).")
    ],
    robot: Annotated[
        str, typer.Option(help="ur (with --cell), plant, or twin (the ideal simulation).")
    ] = "ur",
    cell: CellOption = None,
    emulated: EmulatedOption = False,
    effects: PlantEffects = None,
    yes: Annotated[bool, typer.Option("--yes", help="Start without asking to confirm.")] = False,
    rerun: Annotated[
        Path | None, typer.Option(help="Write the logged and the replayed episode, overlaid, here.")
    ] = None,
) -> None:
    """Re-send a logged episode's joint targets through the safety layer, after showing
    its start pose and asking to confirm; record the replay (source ``replay``)."""
    from twinrl_data.recorder import Recorder
    from twinrl_data.session import Session
    from twinrl_data.sources import open_episode
    from twinrl_robot.backends import ROBOTS, open_robot
    from twinrl_robot.cell_file import load_cell
    from twinrl_robot.replay_source import replay_episode
    from twinrl_sim.tasks import make_task, task_on_twin

    if robot not in ROBOTS:
        raise UsageError(f"--robot must be one of {', '.join(ROBOTS)}, got '{robot}'")
    world = ROBOTS[robot]
    if world == "real" and cell is None:
        raise UsageError("--robot ur needs the arm's --cell file")
    if (cell is not None or emulated) and world != "real":
        raise UsageError("--cell and --emulated describe a UR arm; add --robot ur")
    logged = open_episode(episode)
    # On a cell, the task on the cell's own twin (the IK and the limits the arm runs with).
    twin = task_on_twin(logged.meta.task, load_cell(cell).twin) if cell is not None else None
    task = make_task(logged.meta.task, twin)
    arm = open_robot(
        world,
        task,
        effects=effects if world == "plant" else None,
        effort=world != "twin",
        object_poses=world != "real" or emulated,
        cell=cell,
        emulated=emulated,
    )
    recorder = Recorder(Session.create(out, exist_ok=True))
    confirm = None if yes else lambda start: typer.confirm(f"Move the arm to {start}?")
    try:
        result = replay_episode(arm, logged, task, recorder, confirm)
    finally:
        arm.close()
    console.print(
        f"{result.path}: {result.steps} steps replayed; the joints ran "
        f"{result.joint_rms * 1000:.2f} mrad RMS from the log"
    )
    if rerun is not None:
        from twinrl_data.view import save_rrd
        from twinrl_sim.cli.view import twin_cell

        replayed = open_episode(result.path)
        save_rrd([logged, replayed], rerun, cell=twin_cell(logged), force=True)
        console.print(f"{rerun}: the logged and the replayed episode, overlaid")
