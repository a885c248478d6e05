"""What the command groups share: the console and the parser of integer lists."""

from __future__ import annotations

from rich.console import Console

from twinrl_data.errors import UsageError

console = Console(soft_wrap=True)  # paths and figures are never broken across lines


def parse_ints(text: str, flag: str) -> tuple[int, ...]:
    try:
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise UsageError(
            f"{flag} takes comma-separated integers, e.g. 0,1,2; got '{text}'"
        ) from None
