"""Which joint torques an RTDE log gives: the controller's commanded torques, its
measured currents as torques, or raw currents with the drives' torque constants; the
import says which, and refuses what the log cannot give."""

import numpy as np
import pytest

from twinrl_data import schema as contract
from twinrl_data.errors import DataError, SettingError
from twinrl_data.importers import import_csv, rtde_map

BASE = ["timestamp", *(f"{k}_{i}" for k in ("target_q", "actual_q", "actual_qd") for i in range(6))]
TCP = [f"actual_TCP_pose_{i}" for i in range(6)]


def _log(tmp_path, torques: dict[str, np.ndarray]) -> str:
    """A 40-row RTDE log with the given torque-like columns (name prefix -> (rows, 6))."""
    columns = BASE + TCP + [f"{k}_{i}" for k in torques for i in range(6)]
    rows = []
    for t in range(40):
        q = np.sin(0.05 * t + np.arange(6))
        values = [t * 0.008, *q, *q, *np.cos(0.05 * t + np.arange(6))]
        values += [0.4, 0.1, 0.3, 0.0, 3.1, 0.0]
        for array in torques.values():
            values += list(array[t])
        rows.append(",".join(f"{v:.6f}" for v in values))
    path = tmp_path / "log.csv"
    path.write_text("\n".join([",".join(columns), *rows]) + "\n")
    return path


def _effort(path, cmap) -> np.ndarray:
    return import_csv(path, cmap).data[contract.EFFORT]


def test_the_commanded_torques_come_first_then_the_measured_ones(tmp_path):
    rng = np.random.default_rng(0)
    moment, as_torque = rng.normal(size=(40, 6)), rng.normal(size=(40, 6))
    both = _log(tmp_path, {"target_moment": moment, "actual_current_as_torque": as_torque})
    cmap, said = rtde_map(both)
    assert "target_moment" in said
    np.testing.assert_allclose(_effort(both, cmap), moment, atol=1e-5)
    cmap, said = rtde_map(both, "current_as_torque")
    assert "actual_current_as_torque" in said
    np.testing.assert_allclose(_effort(both, cmap), as_torque, atol=1e-5)
    only_measured = _log(tmp_path, {"actual_current_as_torque": as_torque})
    cmap, said = rtde_map(only_measured)
    assert "actual_current_as_torque" in said


def test_raw_currents_need_the_torque_constants(tmp_path):
    current = np.random.default_rng(1).normal(size=(40, 6))
    path = _log(tmp_path, {"actual_current": current})
    cmap, said = rtde_map(path)
    assert said.startswith("no joint torques")
    assert contract.EFFORT not in import_csv(path, cmap).data
    with pytest.raises(SettingError, match="torque constants"):
        rtde_map(path, "current")
    constants = [13.0, 13.0, 9.0, 4.5, 4.5, 4.5]
    cmap, said = rtde_map(path, "auto", constants)
    assert "actual_current (A)" in said
    np.testing.assert_allclose(_effort(path, cmap), current * constants, atol=1e-4)
    with pytest.raises(SettingError, match="needs 6 numbers"):
        rtde_map(path, "current", constants[:5])
    with pytest.raises(DataError, match="needs column.*target_moment_0"):
        rtde_map(path, "target_moment")
    with pytest.raises(SettingError, match="must be one of"):
        rtde_map(path, "amps")


def test_the_command_line_says_which_torques_and_refuses_what_the_log_lacks(tmp_path):
    from typer.testing import CliRunner

    from twinrl_learn.cli import app

    current = np.random.default_rng(2).normal(size=(40, 6))
    path = _log(tmp_path, {"actual_current": current})
    out = tmp_path / "session"
    refused = CliRunner().invoke(
        app, ["data", "import-csv", str(path), "--out", str(out), "--torque", "current"]
    )
    assert refused.exit_code != 0
    assert "torque constants" in str(refused.exception) + refused.output
    assert not out.exists()
    constants = "13 13 9 4.5 4.5 4.5"
    done = CliRunner().invoke(
        app, ["data", "import-csv", str(path), "--out", str(out), "--torque-constants", constants]
    )
    assert done.exit_code == 0, done.output
    assert "joint torques from actual_current (A) times the given torque constants" in done.output
