"""``twinrl expand``: synthesize demonstrations in the twin."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from twinrl_data.console import progress, quiet_encoders

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.settings_cli import name_flags
from twinrl_sim.cli.common import ClusterOption, console
from twinrl_sim.randomize import KINDS as RANDOMIZATIONS
from twinrl_sim.tasks import TASKS, task_on_twin

name_flags(id_count="--id", ood_count="--ood")

if TYPE_CHECKING:
    pass


def expand_command(
    task: Annotated[str, typer.Argument(help=f"Task: {', '.join(TASKS)}.")],
    out: Annotated[Path, typer.Option(help="Folder for the session, the dataset and expand.json.")],
    id_count: Annotated[
        int, typer.Option("--id", help="Demonstrations in the ID region.", min=0)
    ] = 30,
    ood_count: Annotated[
        int, typer.Option("--ood", help="Demonstrations in the OOD region.", min=0)
    ] = 30,
    method: Annotated[
        str, typer.Option(help="plan (grasp sampling + planner) or augment.")
    ] = "plan",
    from_demo: Annotated[
        Path | None, typer.Option(help="Recorded demonstration (.mcap) to re-target with augment.")
    ] = None,
    randomize: Annotated[
        str,
        typer.Option(
            help=f"Visual randomisation: comma-separated {', '.join(RANDOMIZATIONS)}, or all."
        ),
    ] = "",
    twin: Annotated[
        str | None,
        typer.Option(
            help="Scene spec to synthesize in (e.g. twin_fitted.yaml from `gap diagnose`, "
            "with the cell's physics and look); default: the task's built-in cell."
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option(help="Seed (attempt k always gets the same configuration).")
    ] = 0,
    workers: Annotated[
        int | None,
        typer.Option(help="Workers (default: 2; on a cluster, one per CPU).", min=1),
    ] = None,
    images: Annotated[
        bool,
        typer.Option(
            help="Render and record the front and wrist cameras; --no-images for demos a "
            "state policy learns from (several times faster)."
        ),
    ] = True,
    detours: Annotated[
        float,
        typer.Option(
            help="Share of the demos (plan only) whose arm first strays to a point 8-20 cm "
            "beside the object and does the task from there: views off the straight path, "
            "and the way back, for an image policy.",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    misses: Annotated[
        float,
        typer.Option(
            help="Share of the demos (plan only) whose first grasp closes 2-4.5 cm above the "
            "object, lifts empty-handed, opens and grasps again: closed empty fingers and the "
            "recovery, for a pose estimator or an image policy.",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    closed_detours: Annotated[
        float,
        typer.Option(
            help="Share of the detours made with the fingers closed, opened on the way back: "
            "closed fingers holding nothing, away from the object, for a pose estimator "
            "(not for a policy's demos: it would learn to close them there).",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    force: Annotated[bool, typer.Option(help="Replace --out if it exists.")] = False,
    cluster: ClusterOption = "",
) -> None:
    """Synthesize twin demonstrations across ID and OOD (TwinRL's exploration-space expansion)."""
    from twinrl_sim.expand import expand

    kinds = RANDOMIZATIONS if randomize == "all" else tuple(k for k in randomize.split(",") if k)
    scene = task_on_twin(task, twin) if twin is not None else None
    quiet_encoders()
    with progress("kept") as bar:
        jobs = {
            "ID": bar.add_task(f"{task} ID attempts", total=None, kept=0),
            "OOD": bar.add_task(f"{task} OOD attempts", total=None, kept=0),
        }
        kept = {"ID": 0, "OOD": 0}

        def advance(region: str, success: bool) -> None:
            kept[region] += success
            bar.update(jobs[region], advance=1, kept=kept[region])

        report = expand(
            task,
            id_count=id_count,
            ood_count=ood_count,
            out=out,
            method=method,
            from_demo=from_demo,
            randomize=kinds,
            scene=scene,
            seed=seed,
            workers=workers,
            images=images,
            detours=detours,
            misses=misses,
            closed_detours=closed_detours,
            force=force,
            on_demo=advance,
            cluster=cluster,
        )
    table = Table(
        "region", "requested", "kept", "attempts", "yield", title=f"{task}: {method} demonstrations"
    )
    for region, requested in report.requested.items():
        table.add_row(
            region,
            str(requested),
            str(report.kept.get(region, 0)),
            str(report.attempts.get(region, 0)),
            f"{100 * report.yield_rate[region]:.0f} %",
        )
    console.print(table)
    if detours:
        closed = f" ({sum(report.closed.values())} with closed fingers)" if closed_detours else ""
        console.print(f"{sum(report.detoured.values())} of the kept demos stray first{closed}")
    if misses:
        console.print(f"{sum(report.missed.values())} of the kept demos miss their first grasp")
    console.print(
        f"synthesis {report.seconds_synthesis:.1f} s, export {report.seconds_export:.1f} s; "
        f"episodes in {report.session}, dataset {report.dataset or '(none)'}"
    )
