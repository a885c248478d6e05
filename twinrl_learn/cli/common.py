"""What the command groups share: the console and the parsers of list-like options."""

from __future__ import annotations

from rich.console import Console

from twinrl_data.errors import UsageError

console = Console(soft_wrap=True)  # paths and figures are never broken across lines


def parse_grid(text: str, flag: str = "--grid") -> tuple[int, int]:
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"{flag} must look like 8x8, got '{text}'") from None
    if rows < 1 or cols < 1:
        raise UsageError(f"{flag} needs positive sizes, got '{text}'")
    return rows, cols


def parse_ints(text: str, flag: str) -> tuple[int, ...]:
    try:
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise UsageError(
            f"{flag} takes comma-separated integers, e.g. 0,1,2; got '{text}'"
        ) from None
