"""Options derived from settings dataclasses: one record is the config, the CLI and the help."""

import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from twinrl_data.errors import DataError, SettingError, UsageError
from twinrl_data.settings_cli import (
    describe,
    field_docs,
    name_flags,
    options,
    parse_grid,
    settings_command,
)

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Inner:
    rate: float = 0.5
    """How fast."""


@dataclass
class Run:
    name: str
    """What the run is called."""
    steps: int | None = None
    """Steps (default: the method's)."""
    sources: list[str] = field(default_factory=list)
    """Where the data is; repeatable."""
    grid: tuple[int, int] = (4, 4)
    """Evaluation grid."""
    weights: list[float] | None = None
    """Weight per source."""
    fast: bool = False
    """Go fast."""
    inner: Inner = field(default_factory=Inner)
    """Nested settings."""

    def __post_init__(self) -> None:
        if self.steps is not None and self.steps < 1:
            raise SettingError("steps", f"must be at least 1, got {self.steps}")


@dataclass
class Undocumented:
    quiet: int = 0


def test_a_fields_docstring_is_its_help():
    assert field_docs(Run)["sources"] == "Where the data is; repeatable."
    with pytest.raises(TypeError, match="Undocumented.quiet has no docstring"):
        options(Undocumented)


def test_a_command_built_from_a_record_parses_every_kind_of_field():
    got = {}
    app = typer.Typer()

    def run(settings, dry):
        inner = Inner(**settings.pop("inner"))
        got["run"] = Run(**settings, inner=inner)
        got["dry"] = dry

    import inspect
    from typing import Annotated

    dry = inspect.Parameter(
        "dry", inspect.Parameter.KEYWORD_ONLY, annotation=Annotated[bool, typer.Option()],
        default=False,
    )  # fmt: skip
    made = [*options(Run, names={"sources": "source"}), *options(Inner, prefix="inner")]
    settings_command(app, "go", [o for o in made if o.name != "inner"], run, help="Go.",
                     extra=[dry])  # fmt: skip
    result = CliRunner().invoke(
        app,
        ["--name", "a", "--source", "x", "--source", "y", "--grid", "2x3", "--weights", "1,2",
         "--fast", "--rate", "0.1", "--dry"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert got["run"] == Run("a", None, ["x", "y"], (2, 3), [1.0, 2.0], True, Inner(0.1))
    assert got["dry"] is True
    helped = CliRunner().invoke(app, ["--help"], env={"COLUMNS": "200"})
    assert "Where the data is; repeatable." in helped.output and "--no-fast" in helped.output
    bad = CliRunner().invoke(app, ["--name", "a", "--steps", "0"])
    assert isinstance(bad.exception, SettingError)
    assert describe(bad.exception) == "--steps must be at least 1, got 0"
    assert str(bad.exception) == "steps must be at least 1, got 0"  # the library's words


def test_grids_are_rows_by_columns():
    assert parse_grid("8x4") == (8, 4)
    for text in ("8", "0x3", "axb"):
        with pytest.raises(UsageError, match="grid"):
            parse_grid(text)


def test_settings_named_in_a_message_are_named_by_their_flags_on_the_command_line():
    name_flags(id_count="--id")
    error = DataError("out already exists; choose another folder or replace it (`force`)")
    assert describe(error) == "out already exists; choose another folder or replace it (--force)"
    both = SettingError("detours", "needs `id_count` above 0 and `method` plan")
    assert describe(both) == "--detours needs --id above 0 and --method plan"
    assert str(both) == "detours needs `id_count` above 0 and `method` plan"


def test_no_library_message_names_a_command_line_flag():
    """Library code speaks of settings (the CLI turns them into flags), never of flags."""
    flag = re.compile(r"['\"][^'\"\n]*\s--[a-z][a-z-]+")
    offenders = []
    for package in ("twinrl_data", "twinrl_sim", "twinrl_robot", "twinrl_learn"):
        for path in (ROOT / package).rglob("*.py"):
            if "cli" in path.parts or path.name == "cli.py" or path.name.endswith("_cli.py"):
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                message = line.strip().startswith(('f"', '"', "raise")) or "Error(" in line
                if message and flag.search(line) and "help=" not in line:
                    offenders.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
