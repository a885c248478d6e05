"""``twinrl demo``: the whole pipeline against its baselines."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from twinrl_data.console import progress, quiet_encoders
from twinrl_data.errors import UsageError
from twinrl_data.settings_cli import parse_ints
from twinrl_learn.cli.common import DeviceOption, console
from twinrl_sim.cli.common import ClusterOption
from twinrl_sim.tasks import TASKS, make_task

if TYPE_CHECKING:
    from twinrl_learn.studies.pipeline import RunProgress


def demo_command(
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")] = "pick_place",
    preset: Annotated[
        str,
        typer.Option(
            help="smoke (every stage, minutes), quick (state policy, ~16 min), quick-vision "
            "(nothing privileged: the image policy through a pose estimator, success from a "
            "classifier, the simulated person judging from what it sees) or paper (image "
            "policy; about 12 hours of RL updates on 2 cores, 5 on an H100: meant for a GPU, "
            "see --device)."
        ),
    ] = "quick",
    out: Annotated[Path, typer.Option(help="Folder for the report, logs and policies.")] = Path(
        "out/twinrl_demo"
    ),
    seeds: Annotated[
        str | None, typer.Option(help="Comma-separated seeds (default: the preset's three).")
    ] = None,
    inputs: Annotated[
        str | None,
        typer.Option(
            help="State policy's inputs: absolute or relative (see train sft; default: the "
            "preset's: relative in quick, absolute in smoke)."
        ),
    ] = None,
    workers: Annotated[
        int,
        typer.Option(
            help="Real-RL runs side by side (a process each, or a Ray task each on --cluster).",
            min=1,
        ),
    ] = 2,
    resume: Annotated[
        bool, typer.Option(help="Continue a stopped run in --out (finished stages are kept).")
    ] = False,
    device: DeviceOption = "auto",
    cluster: ClusterOption = "",
) -> None:
    """The whole TwinRL pipeline in the plant, then its baselines; report.md and .json.

    The baselines (HiL-SERL, ConRFT-style and TwinRL without the twin buffer) run on
    the same plant and seeds."""
    import torch

    from twinrl_learn.studies.pipeline import run_demo
    from twinrl_learn.studies.presets import PRESETS

    make_task(task)
    if preset not in PRESETS:
        raise UsageError(f"--preset must be one of {', '.join(PRESETS)}, got '{preset}'")
    chosen = parse_ints(seeds, "--seeds") if seeds else None
    torch.set_num_threads(1)
    quiet_encoders()
    with progress("ID", "OOD") as bar:
        jobs: dict[tuple[str, int], int] = {}
        steps = PRESETS[preset].plant_steps

        def on_progress(run: RunProgress) -> None:
            key = (run.method, run.seed)
            if key not in jobs:
                jobs[key] = bar.add_task(
                    f"{run.method}, seed {run.seed}", total=steps, ID="-", OOD="-"
                )
            bar.update(
                jobs[key],
                completed=min(run.plant_steps, steps),
                **{r: f"{100 * v:.0f} %" for r, v in run.success_rate.items()},
            )

        report = run_demo(
            task,
            preset,
            out,
            seeds=chosen,
            inputs=inputs,
            workers=workers,
            resume=resume,
            device=device,
            log=lambda text: bar.console.print(text),
            on_progress=on_progress,
            cluster=cluster,
        )
    table = Table("method", "min to 95 % ID", "min to 95 % OOD", "final ID", "final OOD", "interv.")
    for name, m in report["methods"].items():
        to95 = m["plant_minutes_to_95"]
        table.add_row(
            name,
            *("-" if to95[r] is None else f"{to95[r]:.1f}" for r in ("ID", "OOD")),
            *(f"{100 * m['final_success'][r]:.0f} %" for r in ("ID", "OOD")),
            str(m["interventions"]),
        )
    console.print(table)
    console.print(f"report: {out / 'report.md'}")
