"""``twinrl bench``: the paper's experiments (Table I, the stages study), their options
derived from the studies' settings records
(:class:`~twinrl_learn.studies.settings.Stage1Settings`,
:class:`~twinrl_learn.studies.settings.StagesSettings`)."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Annotated, Any

import typer

from twinrl_data.console import progress, quiet_encoders
from twinrl_data.settings_cli import options, settings_command
from twinrl_learn.cli.common import console
from twinrl_learn.studies.settings import Stage1Settings, StagesSettings

app = typer.Typer(help="Reproduce the paper's experiments.", no_args_is_help=True)

OUT = inspect.Parameter(
    "out",
    inspect.Parameter.KEYWORD_ONLY,
    annotation=Annotated[
        Path, typer.Option(help="Folder for datasets, policies, heatmaps, table1.md.")
    ],
)


def stage1(settings: dict[str, Any], out: Path) -> None:
    from twinrl_learn.studies.table1 import run_stage1

    config = Stage1Settings(**settings)
    quiet_encoders()
    run_stage1(config, out, log=lambda line: console.print(line))
    console.print((out / "table1.md").read_text())


STAGE1_FIELDS = (
    "tasks", "policies", "scale", "grid", "episodes_per_cell", "seed", "vla_steps",
    "state_steps", "act_steps", "fit_look", "detours", "perception", "state_inputs", "device",
)  # fmt: skip
settings_command(
    app,
    "stage1",
    options(
        Stage1Settings,
        only=STAGE1_FIELDS,
        names={"episodes_per_cell": "episodes", "state_inputs": "inputs"},
    ),
    stage1,
    help="TwinRL's Table I in the plant: real-only SFT vs real + twin ID/OOD demos.",
    extra=[OUT],
)

RUN = inspect.Parameter(
    "run",
    inspect.Parameter.KEYWORD_ONLY,
    annotation=Annotated[
        Path,
        typer.Argument(
            help="A `twinrl demo` run folder (Stage II done).", metavar="RUN", show_default=False
        ),
    ],
)


def stages(settings: dict[str, Any], run: Path) -> None:
    import torch

    from twinrl_learn.studies.stages import measure_stages

    config = StagesSettings(run=run, **settings)
    torch.set_num_threads(1)
    quiet_encoders()
    with progress() as bar:
        task = bar.add_task("measuring", total=None)

        def on_evaluation(done: int, total: int, label: str) -> None:
            bar.update(task, completed=done, total=total, description=label)

        measure_stages(config, on_evaluation=on_evaluation)
    console.print((config.out / "stages.md").read_text(), markup=False)


settings_command(
    app,
    "stages",
    options(
        StagesSettings, only=("out", "seeds", "grid", "episodes", "finals", "workers", "cluster")
    ),
    stages,
    help="What each stage of a pipeline run adds, on many plant episodes per policy: the "
    "Stage I and Stage II policies, the Stage II policy after the real-RL offline phase "
    "with and without the twin buffer, and the TwinRL runs' final policies, all on the "
    "same plant configurations (paired by seed).",
    extra=[RUN],
)
