"""Imports only point down: twinrl_data < twinrl_sim < twinrl_robot < twinrl_learn."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["twinrl_data", "twinrl_sim", "twinrl_robot", "twinrl_learn"]


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names & set(LAYERS)


@pytest.mark.parametrize("layer", LAYERS)
def test_no_module_imports_a_higher_layer(layer):
    allowed = set(LAYERS[: LAYERS.index(layer) + 1])
    files = list((ROOT / layer).rglob("*.py"))
    assert files, f"{layer} has no modules"
    offenders = {
        str(f.relative_to(ROOT)): sorted(imported_packages(f) - allowed)
        for f in files
        if imported_packages(f) - allowed
    }
    assert not offenders, f"imports pointing up: {offenders}"


def test_the_checker_catches_an_upward_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from twinrl_learn.cli import app\nimport twinrl_robot.plant\n")
    assert imported_packages(bad) == {"twinrl_learn", "twinrl_robot"}


def module_imports(path: Path, modules: set[str]) -> set[str]:
    """The project modules ``path`` imports anywhere (type-checking and lazy imports too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                found.add(full if full in modules else node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found & modules


def test_no_two_modules_import_each_other_even_indirectly():
    files = {
        ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): f
        for layer in LAYERS
        for f in (ROOT / layer).rglob("*.py")
    }
    graph = {name: module_imports(path, set(files)) for name, path in files.items()}
    cycles = []
    for start in graph:  # a depth-first walk from each module back to itself
        stack, seen = [(start, [start])], set()
        while stack:
            node, path = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    cycles.append(path)
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*path, nxt]))
    assert not cycles, f"import cycles: {sorted({' -> '.join(c) for c in cycles})[:5]}"
