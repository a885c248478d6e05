"""MkDocs hook: render the command-line reference from the `twinrl` command itself.

A page that holds the line ``<!-- twinrl-cli-reference -->`` gets, in its place, one
section per command and subcommand of the root Typer app (`twinrl_learn.cli.app`):
its help, its usage line and a table of its arguments and options, each with its
help, default and range as `twinrl ... --help` prints them. The reference is built
from the commands at every build, so it cannot drift from them.
"""

from __future__ import annotations

import inspect
import re
from typing import Any

MARKER = "<!-- twinrl-cli-reference -->"


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, render_reference())


def render_reference() -> str:
    import typer

    from twinrl_learn.cli import app

    root = typer.main.get_command(app)
    ctx = root.context_class(root, info_name="twinrl")
    lines: list[str] = []
    _render(root, ctx, ["twinrl"], 1, lines)
    return "\n".join(lines) + "\n"


def _render(command: Any, ctx: Any, path: list[str], level: int, lines: list[str]) -> None:
    title = " ".join(path)
    anchor = "-".join(path)
    if level > 1:  # the root's heading is the page's own
        lines += [f"{'#' * level} `{title}` {{ #{anchor} }}", ""]
    if command.help:
        lines += [_text(inspect.cleandoc(command.help)), ""]
    usage = command.get_usage(ctx).strip()
    lines += ["```text", usage, "```", ""]
    rows = [_param_row(param, ctx) for param in command.get_params(ctx)]
    rows = [row for row in rows if row is not None]
    if rows:
        lines += ["| argument or option | description |", "|---|---|"]
        lines += [f"| `{name}` | {_cell(text)} |" for name, text in rows]
        lines.append("")
    if hasattr(command, "list_commands"):
        names = [
            name
            for name in command.list_commands(ctx)
            if not getattr(command.get_command(ctx, name), "hidden", False)
        ]
        lines += ["| command | description |", "|---|---|"]
        for name in names:
            sub = command.get_command(ctx, name)
            link = f"[`{name}`](#{anchor}-{name})"
            lines.append(f"| {link} | {_cell(sub.get_short_help_str(limit=300))} |")
        lines.append("")
        for name in names:
            sub = command.get_command(ctx, name)
            sub_ctx = sub.context_class(sub, info_name=name, parent=ctx)
            _render(sub, sub_ctx, [*path, name], level + 1, lines)


def _param_row(param: Any, ctx: Any) -> tuple[str, str] | None:
    if getattr(param, "hidden", False) or param.name == "help":
        return None
    record = param.get_help_record(ctx)
    if record is None:
        return None
    name, text = record
    return name, text


_CODE = re.compile(r"(``?[^`]+``?)")


def _text(text: str) -> str:
    """Help text as Markdown: angle brackets escaped outside code spans."""
    parts = _CODE.split(text)
    return "".join(
        part if part.startswith("`") else part.replace("<", "&lt;").replace(">", "&gt;")
        for part in parts
    )


def _cell(text: str) -> str:
    """Help text for a table cell: one line, pipes escaped."""
    return _text(" ".join(text.split())).replace("|", "\\|")
