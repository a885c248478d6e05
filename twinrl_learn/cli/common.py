"""What the command groups share: the console."""

from __future__ import annotations

from rich.console import Console

console = Console(soft_wrap=True)  # paths and figures are never broken across lines
