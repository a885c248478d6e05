"""``twinrl data import-csv``: logs recorded outside twinrl, as episodes (the twin gives
the TCP pose)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.errors import UsageError
from twinrl_data.settings_cli import parse_numbers
from twinrl_sim.cli.common import console
from twinrl_sim.tasks import twin_scene

if TYPE_CHECKING:
    pass


def import_csv_command(
    files: Annotated[list[Path], typer.Argument(help="CSV logs, one episode each.")],
    out: Annotated[Path, typer.Option(help="Session folder to create with the episodes.")],
    format: Annotated[
        str, typer.Option("--format", help="rtde (UR's RTDE recorder columns) or generic.")
    ] = "rtde",
    column_map: Annotated[
        Path | None,
        typer.Option("--map", help="YAML column map (required with --format generic)."),
    ] = None,
    fps: Annotated[
        float | None, typer.Option(help="Resample to this rate (default: the log's own).")
    ] = None,
    twin: Annotated[
        str,
        typer.Option(help="Built-in cell or scene spec whose robot computes missing TCP poses."),
    ] = "pick_place",
    world: Annotated[str, typer.Option(help="real or plant: where the log was measured.")] = "real",
    tcp_offset: Annotated[
        str | None,
        typer.Option(
            help="The TCP set on the controller when the log was taken, 'x y z rx ry rz' "
            "(m, axis-angle rad, flange frame; the cell file's arm.tcp_offset): the logged "
            "TCP poses are converted to the twin's TCP so both compare one point."
        ),
    ] = None,
    task: Annotated[str, typer.Option(help="Task label of the episodes.")] = "arm",
    torque: Annotated[
        str,
        typer.Option(
            help="rtde: which joint torques to read: auto (target_moment, else "
            "actual_current_as_torque, else actual_current with --torque-constants), "
            "target_moment, current_as_torque, current or none."
        ),
    ] = "auto",
    torque_constants: Annotated[
        str | None,
        typer.Option(
            help="rtde: the drives' torque constants, 6 numbers in N m/A, to read "
            "actual_current as torques."
        ),
    ] = None,
) -> None:
    """Import joint logs recorded outside twinrl as episodes (source ``imported``).

    A generic column map is YAML: ``time``, ``time_unit`` (s|ms|us|ns), ``angle_unit``
    (rad|deg), ``layout`` (wide|long), ``commanded``/``measured`` (one column per joint),
    optional ``velocity``, ``effort`` (N m), ``tcp`` (x y z rx ry rz), ``joints``.
    """
    from twinrl_data.importers import ColumnMap, import_csv, rtde_map
    from twinrl_data.session import Session
    from twinrl_sim.build import compile_scene
    from twinrl_sim.kinematics import ControllerTcp, TcpKinematics

    if format not in ("rtde", "generic"):
        raise UsageError(f"--format must be rtde or generic, got '{format}'")
    if format == "generic" and column_map is None:
        raise UsageError("--format generic needs --map COLUMNS.yaml (see --help for its keys)")
    constants = (
        None
        if torque_constants is None
        else list(parse_numbers(torque_constants, "--torque-constants"))
    )
    if format == "generic" and (torque != "auto" or constants is not None):
        raise UsageError(
            "--torque and --torque-constants apply to --format rtde; a column "
            "map names its torque columns (effort, effort_scale)"
        )
    scene = compile_scene(twin_scene(twin))
    kinematics = TcpKinematics(scene)
    tcp_frame = None
    if tcp_offset is not None:
        offset = parse_numbers(tcp_offset, "--tcp-offset")
        if len(offset) != 6:
            raise UsageError(f"--tcp-offset needs 6 numbers (x y z rx ry rz), got {len(offset)}")
        tcp_frame = ControllerTcp(scene, list(offset))
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"{out} exists and is not empty; choose another --out")
    generic = ColumnMap.load(column_map) if column_map else None
    maps = {f: (generic, None) if generic else rtde_map(f, torque, constants) for f in files}
    episodes = [
        import_csv(
            f,
            maps[f][0],
            fps=fps,
            task=task,
            world=world,
            forward_kinematics=kinematics,
            tcp_frame=tcp_frame,
        )
        for f in files
    ]
    session = Session.create(out)
    for f, episode in zip(files, episodes, strict=True):
        session.add(episode)
        torques = f"; {maps[f][1]}" if maps[f][1] else ""
        console.print(
            f"{episode.meta.policy}: {len(episode)} steps at {episode.meta.fps:g} Hz, "
            f"fields {', '.join(sorted(episode.data))}{torques}"
        )
    console.print(f"{out}: {len(episodes)} episodes imported")
