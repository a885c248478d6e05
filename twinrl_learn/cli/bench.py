"""``twinrl bench``: the paper's experiments (Table I, the stages study)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from twinrl_data.console import progress, quiet_encoders
from twinrl_data.settings_cli import parse_grid
from twinrl_learn.cli.common import console, parse_ints

app = typer.Typer(help="Reproduce the paper's experiments.", no_args_is_help=True)


@app.command("stage1")
def bench_stage1(
    out: Annotated[Path, typer.Option(help="Folder for datasets, policies, heatmaps, table1.md.")],
    tasks: Annotated[
        str, typer.Option(help="Comma-separated tasks.")
    ] = "pick_place,insert_hexagon",
    policies: Annotated[
        str, typer.Option(help="Comma-separated policy kinds: state, vla.")
    ] = "state",
    scale: Annotated[
        float, typer.Option(help="Multiply every demo count (0.1 for a smoke run).")
    ] = 1.0,
    grid: Annotated[str, typer.Option(help="Evaluation grid over ID and OOD.")] = "4x4",
    episodes: Annotated[int, typer.Option(help="Evaluation episodes per grid cell.", min=1)] = 4,
    seed: Annotated[int, typer.Option(help="Seed for demos, SFT and evaluation.")] = 0,
    vla_steps: Annotated[int | None, typer.Option(help="SFT steps of the image policy.")] = None,
    state_steps: Annotated[int | None, typer.Option(help="SFT steps of the state policy.")] = None,
    fit_look: Annotated[
        bool,
        typer.Option(
            help="Fit the twin's appearance (light, table colour) to the real demos' images "
            "(gap diagnose) and synthesize the twin demos in that look."
        ),
    ] = False,
    detours: Annotated[
        float,
        typer.Option(
            help="Share of the twin demos that first stray beside the object (see expand).",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    inputs: Annotated[
        str,
        typer.Option(
            help="The state policy's inputs: relative (objects seen from the TCP) or "
            "absolute (poses in the base frame)."
        ),
    ] = "relative",
) -> None:
    """TwinRL's Table I in the plant: real-only SFT vs real + twin ID/OOD demos."""
    from twinrl_learn.studies.table1 import Stage1Settings, run_stage1

    steps = {k: v for k, v in (("vla", vla_steps), ("state", state_steps)) if v}
    settings = Stage1Settings(
        tasks=tuple(t for t in tasks.split(",") if t),
        policies=tuple(p for p in policies.split(",") if p),
        scale=scale,
        grid=parse_grid(grid, "--grid"),
        episodes_per_cell=episodes,
        steps=steps,
        fit_look=fit_look,
        detours=detours,
        state_inputs=inputs,
        seed=seed,
    )
    quiet_encoders()
    run_stage1(settings, out, log=lambda line: console.print(line))
    console.print((out / "table1.md").read_text())


@app.command("stages")
def bench_stages(
    run: Annotated[Path, typer.Argument(help="A `twinrl demo` run folder (Stage II done).")],
    out: Annotated[Path, typer.Option(help="Folder for stages.md, stages.json, stages.png.")],
    seeds: Annotated[
        str, typer.Option(help="Comma-separated seeds: one evaluation and offline phase each.")
    ] = "0,1,2,3,4",
    grid: Annotated[str, typer.Option(help="Evaluation grid over ID and OOD.")] = "8x8",
    episodes: Annotated[int, typer.Option(help="Evaluation episodes per grid cell.", min=1)] = 2,
    finals: Annotated[
        bool, typer.Option(help="Also measure the final policies of the run's TwinRL runs.")
    ] = True,
) -> None:
    """What each stage of a pipeline run adds, on many plant episodes per policy.

    Measures the Stage I and Stage II policies, the Stage II policy after the real-RL
    offline phase with and without the twin buffer, and the TwinRL runs' final
    policies, all on the same plant configurations (paired by seed)."""
    import torch

    from twinrl_learn.studies.stages import StagesSettings, measure_stages

    settings = StagesSettings(
        run=run,
        out=out,
        seeds=parse_ints(seeds, "--seeds"),
        grid=parse_grid(grid, "--grid"),
        episodes=episodes,
        finals=finals,
    )
    torch.set_num_threads(1)
    quiet_encoders()
    with progress() as bar:
        task = bar.add_task("measuring", total=None)

        def on_evaluation(done: int, total: int, label: str) -> None:
            bar.update(task, completed=done, total=total, description=label)

        measure_stages(settings, on_evaluation=on_evaluation)
    console.print((out / "stages.md").read_text(), markup=False)
