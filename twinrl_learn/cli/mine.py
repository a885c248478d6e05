"""``twinrl mine``: where the policy fails in the twin, as reset targets."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from twinrl_data.settings_cli import parse_grid
from twinrl_learn.cli.common import console
from twinrl_sim.cli.common import ClusterOption
from twinrl_sim.tasks import TASKS, make_task


def mine_command(
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")],
    policy: Annotated[str, typer.Option(help="Policy checkpoint (twinrl or lerobot).")],
    out: Annotated[Path, typer.Option(help="targets.json to write (evaluation goes beside).")],
    episodes_from: Annotated[
        Path | None,
        typer.Option(help="Catalog (Parquet) whose twin evaluations of --policy to reuse."),
    ] = None,
    tau: Annotated[
        float, typer.Option(help="Success below which a configuration is a target.")
    ] = 0.8,
    k: Annotated[int, typer.Option(help="How many targets to keep.", min=1)] = 20,
    grid: Annotated[str, typer.Option(help="Configuration grid over ID and OOD.")] = "8x8",
    episodes: Annotated[int, typer.Option(help="Twin episodes per grid cell.", min=1)] = 2,
    seed: Annotated[int, typer.Option(help="Seed for the evaluation.")] = 0,
    twin: Annotated[
        str | None,
        typer.Option(
            help="The cell's twin to mine in: a scene spec file (or a built-in cell); "
            "default: the task's own scene."
        ),
    ] = None,
    workers: Annotated[
        int, typer.Option(help="Workers sharing the twin episodes, on --cluster too.", min=1)
    ] = 1,
    cluster: ClusterOption = "",
) -> None:
    """Stage III support: where does the policy fail in the twin? Ranked reset targets."""
    from twinrl_learn.mining import mine
    from twinrl_learn.runners import load_runner

    make_task(task)
    runner = load_runner(policy)
    result = mine(
        runner,
        task,
        out=out,
        grid=parse_grid(grid, "--grid"),
        episodes=episodes,
        tau=tau,
        k=k,
        seed=seed,
        catalog=episodes_from,
        twin=twin,
        workers=workers,
        cluster=cluster,
    )
    table = Table("#", "region", "x", "y", "est. success", "score", title=f"targets (tau {tau})")
    for i, target in enumerate(result["targets"], 1):
        table.add_row(
            str(i),
            target["region"],
            f"{target['x']:.3f}",
            f"{target['y']:.3f}",
            f"{100 * target['estimated_success']:.0f} %",
            f"{target['score']:.2f}",
        )
    console.print(table)
    console.print(
        f"{len(result['targets'])} targets from {result['episodes']} twin episodes: {out}"
    )
