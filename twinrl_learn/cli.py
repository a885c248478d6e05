"""The ``twinrl`` command: the root app, assembled from each package's commands."""

from __future__ import annotations

import sys

import typer
from rich.console import Console

from twinrl_data import cli as data_cli
from twinrl_robot import cli as robot_cli
from twinrl_sim import cli as sim_cli
from twinrl_sim.spec import SpecError

app = typer.Typer(
    help="twinrl: digital-twin-guided reinforcement learning for real robot arms.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
sim_cli.app.command("expert")(robot_cli.expert)
app.add_typer(sim_cli.app, name="sim")
app.add_typer(data_cli.app, name="data")
app.command("view")(sim_cli.view)
app.command("expand")(sim_cli.expand_command)

USER_ERRORS = (ValueError, SpecError, FileNotFoundError, KeyError)


def main() -> None:
    """Entry point: user mistakes become one red line and exit status 2."""
    try:
        app()
    except USER_ERRORS as err:
        message = err.args[0] if isinstance(err, KeyError) and err.args else str(err)
        Console(stderr=True).print(f"[red]error:[/red] {message}", highlight=False, soft_wrap=True)
        sys.exit(2)
