"""The terminal of long work: one progress bar style, and encoders kept quiet."""

from __future__ import annotations

import os

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


def quiet_encoders() -> None:
    """Keep video encoders and dataset progress bars off the terminal."""
    os.environ.setdefault("SVT_LOG", "1")
    import av.logging
    import datasets

    av.logging.set_level(av.logging.ERROR)
    datasets.disable_progress_bars()


def progress(*fields: str, disable: bool = False) -> Progress:
    """The progress bar of every long twinrl command (on stderr); ``fields`` are extra
    task fields shown after the count, e.g. ``progress("loss")``."""
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *[TextColumn(f"{name} {{task.fields[{name}]}}") for name in fields],
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
        disable=disable,
    )
