"""Cell files: validated like scene specs, every number bounded, one clear line."""

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.test_cli import twinrl
from twinrl_robot.cell_file import CellFileError, load_cell, parse_cell

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "cell.yaml"


def test_the_documented_example_loads_and_checks():
    cell = load_cell(EXAMPLE)
    assert cell.arm.servo_rate == 500 and cell.gripper.kind == "robotiq_2f85"
    assert [c.name for c in cell.cameras] == ["front", "wrist"]
    result = twinrl("cell", "check", str(EXAMPLE))
    assert result.returncode == 0, result.stderr
    assert "ur5e at 192.168.1.10" in result.stdout and "servoj at 500 Hz" in result.stdout


def test_problems_are_named_with_the_nearest_key_in_one_line(tmp_path):
    data = yaml.safe_load(EXAMPLE.read_text())
    data["safety"]["max_joint_sped"] = 1.0
    data["arm"]["servo_hz"] = 1000
    with pytest.raises(CellFileError) as error:
        parse_cell(data)
    message = str(error.value)
    assert "did you mean 'max_joint_speed'" in message and "servos at 500 Hz at most" in message
    assert "\n" not in message
    bad = tmp_path / "cell.yaml"
    bad.write_text(yaml.safe_dump(data))
    result = twinrl("cell", "check", str(bad))
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert twinrl("cell", "check", str(tmp_path)).stderr.startswith("error: ")


def _leaves(node, path=()):
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _leaves(value, (*path, index))
    else:
        yield path


def test_no_damaged_value_is_accepted_out_of_bounds():
    """Seeded fuzzing: one value replaced by NaN, an infinity, 1e300, a negative, a wrong
    type. Each file is refused in one line, or every number in it is finite and bounded."""
    data = yaml.safe_load(EXAMPLE.read_text())
    paths = list(_leaves(data))
    rng = np.random.default_rng(4)
    values = [float("nan"), float("inf"), -float("inf"), 1e300, -1.0, 0, "x", [], None, 1e6]
    refused = 0
    for _ in range(300):
        changed = copy.deepcopy(data)
        path = paths[int(rng.integers(len(paths)))]
        node = changed
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = values[int(rng.integers(len(values)))]
        try:
            cell = parse_cell(changed)
        except CellFileError as error:
            assert "\n" not in str(error)
            refused += 1
            continue
        numbers = [v for v in _numbers(cell.model_dump())]
        assert all(np.isfinite(v) and abs(v) <= 65535 for v in numbers), path
    assert refused > 200


def _numbers(node):
    if isinstance(node, dict):
        for value in node.values():
            yield from _numbers(value)
    elif isinstance(node, list | tuple):
        for value in node:
            yield from _numbers(value)
    elif isinstance(node, int | float) and not isinstance(node, bool):
        yield float(node)
