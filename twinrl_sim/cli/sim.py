"""``twinrl sim``: look at the simulated cell (render it, list the effects).

The robot package adds ``expert`` and ``excite`` to this group."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.table import Table

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.errors import UsageError
from twinrl_sim.cli.common import console, parse_config, refuse_overwrite
from twinrl_sim.tasks import TASKS

if TYPE_CHECKING:
    pass

app = typer.Typer(
    help="The MuJoCo twin: render cells, run experts, list effects.", no_args_is_help=True
)


@app.command()
def show(
    task: Annotated[str, typer.Argument(help=f"Task: {', '.join(TASKS)}.")],
    config: Annotated[
        str | None, typer.Option(help="Configuration as JSON or a .json file.")
    ] = None,
    region: Annotated[str | None, typer.Option(help="Sample a configuration in ID or OOD.")] = None,
    seed: Annotated[int, typer.Option(help="Seed for the sampled configuration.")] = 0,
    size: Annotated[int, typer.Option(help="Image width and height (pixels).")] = 480,
    out: Annotated[Path | None, typer.Option(help="PNG to write (default: TASK.png).")] = None,
    force: Annotated[bool, typer.Option(help="Overwrite --out if it exists.")] = False,
) -> None:
    """Render the cell of TASK from every camera, side by side, to a PNG."""
    import PIL.Image

    from twinrl_sim.env import TwinEnv

    out = out or Path(f"{task}.png")
    if out.suffix.lower() != ".png":
        raise UsageError(f"--out must end in .png, got {out}")
    refuse_overwrite(out, force)
    env = TwinEnv(task, region=region)
    try:
        options = {"config": parse_config(config)} if config else None
        env.reset(seed=seed, options=options)
        frames = [env.cell.render(cam, width=size, height=size) for cam in env.cell.layout.cameras]
    finally:
        env.close()
    PIL.Image.fromarray(np.hstack(frames)).save(out)
    assert env.config is not None
    console.print(
        f"{out}: {task} ({env.task.region_of(env.config) or 'no region'}) "
        f"config {json.dumps(env.config.to_dict())}, cameras {', '.join(env.cell.layout.cameras)}"
    )


@app.command()
def effects() -> None:
    """List the physical effects the twin and the plant understand."""
    from twinrl_sim.effects import describe_effects

    table = Table("effect", "parameters", "models")
    for name, params, doc in describe_effects():
        table.add_row(name, params, doc)
    console.print(table)
