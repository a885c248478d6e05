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
