"""The ``twinrl`` command: the root app, assembled from each package's commands.

One module per command group: :mod:`.train` (SFT, twin RL, real RL, their options
derived from the settings records), :mod:`.evaluation` (``eval``, ``locate``, ``judge``),
:mod:`.mine`, :mod:`.demo` and :mod:`.bench`; the data, twin and robot commands come
from their own packages. Only what the options' help texts and defaults need loads
here, so that ``twinrl --help`` is quick; each command loads the rest (torch, the
simulator, the datasets) when it runs.
"""

from __future__ import annotations

import sys
import warnings

import typer
from rich.console import Console

from twinrl_data import cli as data_cli
from twinrl_data.errors import DataWarning, TwinrlError
from twinrl_data.settings_cli import describe
from twinrl_learn.cli import bench, demo, evaluation, mine, train
from twinrl_robot import cli as robot_cli
from twinrl_robot import record_cli
from twinrl_robot import robot_cli as robot_commands
from twinrl_sim import cli as sim_cli

app = typer.Typer(
    help="twinrl: digital-twin-guided reinforcement learning for real robot arms.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
sim_cli.app.command("expert")(robot_cli.expert)
sim_cli.app.command("excite")(robot_cli.excite)
app.add_typer(sim_cli.app, name="sim")
app.add_typer(sim_cli.gap_app, name="gap")
app.add_typer(sim_cli.twin_app, name="twin")
app.add_typer(robot_cli.cell_app, name="cell")
app.add_typer(robot_commands.robot_app, name="robot")
data_cli.app.command("import-csv")(sim_cli.import_csv_command)  # needs the twin for FK
app.add_typer(data_cli.app, name="data")
app.command("record")(record_cli.record)
app.command("replay")(robot_commands.replay)
app.command("view")(sim_cli.view)
app.command("expand")(sim_cli.expand_command)
app.add_typer(train.app, name="train")
app.command("eval")(evaluation.eval_command)
app.command("locate")(evaluation.locate_command)
app.command("judge")(evaluation.judge_command)
app.command("demo")(demo.demo_command)
app.command("mine")(mine.mine_command)
app.add_typer(bench.app, name="bench")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A :class:`DataWarning` as one yellow line; other warnings as Python shows them."""
    if issubclass(category, DataWarning):
        Console(stderr=True).print(f"[yellow]warning:[/yellow] {message}", highlight=False)
    else:
        _python_show_warning(message, category, filename, lineno, file, line)


_python_show_warning = warnings.showwarning


def main() -> None:
    """Entry point: the project's errors (bad input of any kind) become one red line and
    exit status 2, a setting named by its flag; anything else is a bug and keeps its
    traceback. Data warnings (a session whose manifest disagrees with its files) are one
    yellow line each."""
    warnings.showwarning = _show_warning
    try:
        app()
    except TwinrlError as err:
        message = describe(err)
        Console(stderr=True).print(f"[red]error:[/red] {message}", highlight=False, soft_wrap=True)
        sys.exit(2)
