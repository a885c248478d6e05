"""Command-line options derived from settings dataclasses.

One dataclass is the configuration, the command line and the help, as CleanRL's
``Args`` is with tyro: a field's help is its docstring (the string written right under
it in the class body), its flag is its name (``plant_steps`` -> ``--plant-steps``), its
default the field's. :func:`options` turns fields into :class:`Option` records (nested
settings flatten, e.g. ``rl.utd`` -> ``--utd``); :func:`settings_command` registers a
typer command whose parameters are those options plus any the command adds, and hands
the values, nested as the settings are, to a function that builds and runs them.

Field types map to options: ``bool`` -> ``--x/--no-x``; ``int``, ``float``, ``str`` and
their ``| None`` forms as they are; ``list[str]`` and ``tuple[str, ...]`` -> a
repeatable option; ``tuple[int, int]`` -> ``AxB`` (a grid); ``list[float] | None`` ->
comma-separated numbers.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import re
import textwrap
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import typer

from twinrl_data.errors import SettingError, TwinrlError, UsageError

# The flag of every setting an option was derived for, by the setting's name: how an
# error about a setting is worded on the command line (see :func:`describe`).
FLAGS: dict[str, str] = {}


@dataclass(frozen=True)
class Option:
    """One command-line option and the settings field it fills."""

    path: str  # dotted path of the field in the settings, e.g. "rl.utd"
    name: str  # the parameter's name; its flag is --name with dashes
    annotation: Any  # the type typer parses
    default: Any
    help: str
    parse: Callable[[Any], Any] | None = None  # the option's value -> the field's


def flag_of(name: str) -> str:
    """The flag of an option named ``name``: ``plant_steps`` -> ``--plant-steps``."""
    return "--" + name.replace("_", "-")


def name_flags(**flags: str) -> None:
    """Record the flags of options that fill a setting of another name
    (``name_flags(id_count="--id")``), so that errors about it name that flag."""
    FLAGS.update(flags)


def describe(error: TwinrlError) -> str:
    """An error as the command line says it: a setting is named by its flag (the flag
    its option was derived with, or the setting's own name as a flag), both the setting
    a :class:`SettingError` is about and every setting a message names in backticks
    (```force``` -> ``--force``)."""
    if isinstance(error, SettingError):
        message = f"{_flag(error.setting)} {error.problem}"
    else:
        message = str(error)
    return SETTING_NAME.sub(lambda match: _flag(match.group(1)), message)


SETTING_NAME = re.compile(r"`([a-z][a-z0-9_]*)`")  # a setting named in a library message


def _flag(setting: str) -> str:
    return FLAGS.get(setting, flag_of(setting))


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstrings of a dataclass's fields (base classes' included), one line each."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0]
        assert isinstance(body, ast.ClassDef)
        for node, following in zip(body.body, body.body[1:], strict=False):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(following, ast.Expr)
                and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)
            ):
                docs[node.target.id] = " ".join(following.value.value.split())
    return docs


def parse_grid(text: str, flag: str = "a grid") -> tuple[int, int]:
    """``"4x4"`` -> ``(4, 4)``; ``flag`` names the option in an error."""
    try:
        rows, cols = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise UsageError(f"{flag} must look like 8x8, got '{text}'") from None
    if rows < 1 or cols < 1:
        raise UsageError(f"{flag} needs positive sizes, got '{text}'")
    return rows, cols


def parse_numbers(text: str, flag: str) -> tuple[float, ...]:
    """``"1,2.5"`` or ``"1 2.5"`` -> ``(1.0, 2.5)``; ``flag`` names the option in an error."""
    try:
        return tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise UsageError(f"{flag} '{text}' must be numbers separated by commas or spaces") from None


def parse_ints(text: str, flag: str) -> tuple[int, ...]:
    """``"0,1,2"`` -> ``(0, 1, 2)``; ``flag`` names the option in an error."""
    try:
        return tuple(int(part) for part in text.replace(",", " ").split())
    except ValueError:
        raise UsageError(
            f"{flag} takes comma-separated integers, e.g. 0,1,2; got '{text}'"
        ) from None


def parse_assignments(values: Sequence[str] | None, flag: str) -> dict[str, str]:
    """``["a=1", "b=x"]`` -> ``{"a": "1", "b": "x"}``; a malformed item is refused by name."""
    parsed = {}
    for value in values or []:
        name, sep, rest = value.partition("=")
        if not sep or not name.strip() or not rest.strip():
            raise UsageError(f"{flag} '{value}' must look like NAME=VALUE")
        parsed[name.strip()] = rest.strip()
    return parsed


def _value_parser(hint: Any, flag: str) -> Callable[[str], Any]:
    """A parser of one option text into a value of type ``hint`` (numbers, paths, text)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis and args[0] in (int, float):
        if args[0] is int:
            return lambda v: parse_ints(v, flag)
        return lambda v: parse_numbers(v, flag)
    if hint is float:

        def one_number(text: str) -> float:
            numbers = parse_numbers(text, flag)
            if len(numbers) != 1:
                raise UsageError(f"{flag} '{text}' must be one number")
            return numbers[0]

        return one_number
    if hint is int:
        return lambda v: _whole(v, flag)
    return hint  # Path, str


def _whole(text: str, flag: str) -> int:
    if not text.strip().lstrip("-").isdigit():
        raise UsageError(f"{flag} '{text}' must be a whole number")
    return int(text)


def _option_type(
    hint: Any, default: Any, flag: str
) -> tuple[Any, Any, Callable[[Any], Any] | None]:
    """(typer type, typer default, parser) for a field's type hint and default."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union) and type(None) in args:
        (inner,) = [a for a in args if a is not type(None)]
        annotation, shown, parse = _option_type(inner, ... if default is None else default, flag)
        if parse is None:
            return inner | None, default, None
        shown = None if default is None else shown
        return annotation | None, shown, lambda v: None if v is None else parse(v)
    if origin is list and args == (float,):
        shown = default if default is ... else ",".join(f"{v:g}" for v in default)
        return str, shown, lambda v: list(parse_numbers(v, flag))
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis and args[0] in (int, float):
        shown = default if default is ... else ",".join(f"{v:g}" for v in default)
        return str, shown, _value_parser(hint, flag)
    if origin is tuple and args == (int, int):
        shown = default if default is ... else f"{default[0]}x{default[1]}"
        return str, shown, lambda v: parse_grid(v, flag)
    if origin in (list, tuple) and args and args[0] is str:
        kept = default if default is ... else (list(default) if default else None)
        return list[str], kept, lambda v: list(v or [])
    if origin is dict:
        key, value = (_value_parser(a, flag) for a in args)
        return (
            list[str] | None,
            None,
            lambda v: {key(k): value(x) for k, x in parse_assignments(v, flag).items()},
        )
    return hint, default, None


def options(
    cls: type,
    *,
    only: Sequence[str] | None = None,
    prefix: str = "",
    names: dict[str, str] | None = None,
    defaults: dict[str, Any] | None = None,
) -> list[Option]:
    """Options for the fields of ``cls`` (``only`` these, in that order), their paths
    under ``prefix``; ``names`` renames a field's option (``datasets`` -> ``dataset``, a
    repeatable flag), ``defaults`` overrides a field's own (a default of ``None`` leaves
    the field to the settings' own choice, e.g. a method's)."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    by_name = {f.name: f for f in dataclasses.fields(cls)}
    chosen = list(only) if only is not None else list(by_name)
    made = []
    for name in chosen:
        field = by_name[name]
        if defaults and name in defaults:
            default = defaults[name]
        elif field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            default = ...  # required
        hint = hints[name]
        if default is None and typing.get_origin(hint) not in (types.UnionType, typing.Union):
            hint = hint | None
        option_name = (names or {}).get(name, name)
        FLAGS[name] = flag_of(option_name)
        annotation, option_default, parse = _option_type(hint, default, FLAGS[name])
        text = docs.get(name)
        if not text:
            raise TypeError(f"{cls.__name__}.{name} has no docstring to serve as its help")
        made.append(
            Option(
                path=f"{prefix}.{name}" if prefix else name,
                name=option_name,
                annotation=annotation,
                default=option_default,
                help=text,
                parse=parse,
            )
        )
    return made


def nested(values: dict[str, Any]) -> dict[str, Any]:
    """``{"rl.utd": 2, "out": "x"}`` -> ``{"rl": {"utd": 2}, "out": "x"}``."""
    tree: dict[str, Any] = {}
    for path, value in values.items():
        *parents, leaf = path.split(".")
        node = tree
        for parent in parents:
            node = node.setdefault(parent, {})
        node[leaf] = value
    return tree


def settings_command(
    app: typer.Typer,
    name: str,
    made: Sequence[Option],
    run: Callable[..., None],
    *,
    help: str,
    extra: Sequence[inspect.Parameter] = (),
) -> None:
    """Register ``name`` on ``app``: its options are ``made`` then ``extra`` (plain typer
    parameters). On a call, ``run`` gets the options' values nested by their paths (as
    ``settings=``) and the extra parameters by name."""
    app.command(name)(settings_function(name, made, run, help=help, extra=extra))


def settings_function(
    name: str,
    made: Sequence[Option],
    run: Callable[..., None],
    *,
    help: str,
    extra: Sequence[inspect.Parameter] = (),
) -> Callable[..., None]:
    """The command function :func:`settings_command` registers, for an app that
    registers it itself (``app.command(name)(function)``)."""
    seen = [o.name for o in made] + [p.name for p in extra]
    doubled = sorted({n for n in seen if seen.count(n) > 1})
    if doubled:
        raise TypeError(f"command {name}: options {doubled} are declared twice")
    parameters = []
    for option in made:
        info = typer.Option(help=option.help, show_default=option.default is not None)
        default = inspect.Parameter.empty if option.default is ... else option.default
        parameters.append(
            inspect.Parameter(
                option.name,
                inspect.Parameter.KEYWORD_ONLY,
                annotation=Annotated[option.annotation, info],
                default=default,
            )
        )
    parameters += [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in extra]
    by_name = {o.name: o for o in made}

    def command(**given: Any) -> None:
        values = {}
        for key, value in given.items():
            option = by_name.get(key)
            if option is not None:
                values[option.path] = option.parse(value) if option.parse else value
        rest = {k: v for k, v in given.items() if k not in by_name}
        run(settings=nested(values), **rest)

    command.__signature__ = inspect.Signature(parameters)  # type: ignore[attr-defined]
    command.__annotations__ = {p.name: p.annotation for p in parameters}
    command.__doc__ = help
    command.__name__ = name.replace("-", "_")
    return command
