"""How long the command line takes to answer, against loading what its commands use.

``twinrl --help`` (and building any command) loads only what the options' help texts
and defaults need; each command loads torch, datasets, rendering and the fitting when it
runs. This times, side by side in fresh interpreters, the bare interpreter, ``twinrl
--help``, ``twinrl train sft --help``, and importing the modules the commands run, which
is what every ``--help`` loaded before the command line loaded them lazily. Usage::

    python bench/bench_cli_startup.py --runs 5
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from typing import Annotated

import typer

# The modules the commands load when they run (the stages, evaluation, the gap workflow,
# synthesis, import, the catalog and the viewer); the twin builder (COLMAP, Open3D) is
# left out: it loaded lazily before too.
COMMAND_MODULES = (
    "twinrl_learn.studies.pipeline",
    "twinrl_learn.studies.table1",
    "twinrl_learn.locating",
    "twinrl_sim.gap.diagnose",
    "twinrl_sim.expand",
    "twinrl_data.importers",
    "twinrl_data.catalog",
    "twinrl_data.view",
)


def seconds(argv: list[str], runs: int) -> float:
    """Median wall time of ``runs`` fresh runs of ``argv``."""
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(argv, check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(
    runs: Annotated[int, typer.Option(help="Fresh interpreters per case.", min=1)] = 5,
) -> None:
    python = sys.executable
    cases = {
        "python -c pass (the interpreter alone)": [python, "-c", "pass"],
        "twinrl --help": [python, "-m", "twinrl_learn", "--help"],
        "twinrl train sft --help": [python, "-m", "twinrl_learn", "train", "sft", "--help"],
        "import the modules the commands run (before)": [
            python,
            "-c",
            f"import {', '.join(COMMAND_MODULES)}",
        ],
    }
    measured = {name: seconds(argv, runs) for name, argv in cases.items()}
    print(f"median of {runs} fresh runs\n\n| case | s |\n|---|---|")
    for name, value in measured.items():
        print(f"| {name} | {value:.2f} |")
    full = measured["import the modules the commands run (before)"]
    print(f"\ntwinrl --help / full import: {measured['twinrl --help'] / full:.2f}")


if __name__ == "__main__":
    typer.run(main)
