"""What the twin's commands share: the console, the --cluster option and the parsers of
their options."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from twinrl_data.errors import UsageError
from twinrl_sim.tasks import TaskConfig

console = Console(soft_wrap=True)  # paths and figures are never broken across lines

ClusterOption = Annotated[
    str,
    typer.Option(
        help="Where the work runs: none (this machine's worker processes; the default unless "
        "RAY_ADDRESS is set), local (Ray embedded here, loopback only), auto (the Ray "
        "cluster this machine joined), HOST:PORT or ray://HOST:PORT (a cluster's head); "
        "see docs/guides/scale-out.md."
    ),
]


def parse_config(text: str) -> TaskConfig:
    """A configuration from inline JSON or from a JSON file path."""
    path = Path(text)
    source = path.read_text() if path.suffix == ".json" and path.is_file() else text
    try:
        data = json.loads(source)
    except json.JSONDecodeError as err:
        raise UsageError(
            "--config must be JSON like "
            '\'{"object": [0.45, -0.2, 0.3], "target": [0.5, -0.1, 0]}\' '
            f"or a .json file ({err.msg})"
        ) from None
    return TaskConfig.from_dict(data)


def refuse_overwrite(path: Path, force: bool) -> None:
    if path.exists() and not force:
        raise UsageError(
            f"{path} already exists; pass --force to overwrite it or choose another --out"
        )
