"""What the command groups share: the console and the --device option."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.console import Console

console = Console(soft_wrap=True)  # paths and figures are never broken across lines

DeviceOption = Annotated[
    str,
    typer.Option(
        help="Where the networks run: auto (a GPU if torch sees one), cpu, cuda or cuda:N."
    ),
]
