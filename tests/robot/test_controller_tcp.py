"""A UR controller's TCP (the tool set on its pendant, in its base frame) and the twin's
TCP are one point once the tool offset is known: the importer's conversion agrees with
the emulator's controller, and an RTDE log imported with --tcp-offset compares with the
twin without the constant offset a tool would leave."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twinrl_data.mcap_log import read_episode
from twinrl_robot.ur.tool_frame import ToolFrame
from twinrl_sim.build import compile_scene
from twinrl_sim.control import rotvec_to_quat
from twinrl_sim.kinematics import ControllerTcp, TcpKinematics
from twinrl_sim.tasks import make_task

OFFSET = [0.01, -0.02, 0.18, 0.0, 0.0, 0.4]  # a long tool, turned on the flange


@pytest.fixture(scope="module")
def scene():
    return compile_scene(make_task("pick_place").scene)


def import_log(log: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    command = ["data", "import-csv", str(log), "--out", str(out), *extra]
    return subprocess.run(
        [sys.executable, "-m", "twinrl_learn", *command],
        capture_output=True,
        text=True,
        timeout=120,
    )


def joint_paths(scene, rows: int, seed: int = 0) -> np.ndarray:
    home = np.array(scene.layout.home_qpos)
    rng = np.random.default_rng(seed)
    return home + np.cumsum(rng.normal(0, 0.01, (rows, len(home))), axis=0)


def test_the_controllers_tcp_maps_onto_the_twins(scene) -> None:
    controller = ToolFrame(scene.model, scene.layout.flange_body, scene.layout.arm_joints, OFFSET)
    twin_tcp = TcpKinematics(scene)
    to_twin = ControllerTcp(scene, OFFSET)
    q = joint_paths(scene, 20)
    logged = np.array([controller.pose(row) for row in q])
    positions, quats = to_twin(logged[:, :3], np.array([rotvec_to_quat(r) for r in logged[:, 3:]]))
    for row, position, quat in zip(q, positions, quats, strict=True):
        expected_position, expected_quat = twin_tcp(row)
        assert np.allclose(position, expected_position, atol=1e-9)
        assert abs(abs(float(quat @ expected_quat)) - 1.0) < 1e-9


def test_an_rtde_log_with_a_tool_imports_into_the_twins_frame(scene, tmp_path: Path) -> None:
    controller = ToolFrame(scene.model, scene.layout.flange_body, scene.layout.arm_joints, OFFSET)
    q = joint_paths(scene, 50, seed=1)
    header = (
        ["timestamp"]
        + [f"target_q_{i}" for i in range(6)]
        + [f"actual_q_{i}" for i in range(6)]
        + [f"actual_qd_{i}" for i in range(6)]
        + [f"target_moment_{i}" for i in range(6)]
        + [f"actual_TCP_pose_{i}" for i in range(6)]
    )
    rows = [
        [t * 0.008, *row, *row, *np.zeros(6), *np.zeros(6), *controller.pose(row)]
        for t, row in enumerate(q)
    ]
    log = tmp_path / "ur.csv"
    log.write_text("\n".join([" ".join(header), *(" ".join(f"{v:.12g}" for v in r) for r in rows)]))
    offset = " ".join(str(v) for v in OFFSET)
    for folder, extra in (("plain", []), ("converted", ["--tcp-offset", offset])):
        result = import_log(log, tmp_path / folder, *extra)
        assert result.returncode == 0, result.stderr
    twin = np.array([TcpKinematics(scene)(row)[0] for row in q])

    def tcp_gap(folder: str) -> float:
        (path,) = (tmp_path / folder).rglob("*.mcap")
        state = read_episode(path, images=False).data["observation.state"]
        return float(np.abs(state[:, 12:15] - twin).max())

    assert tcp_gap("plain") > 0.02, "a tool the twin lacks leaves a constant offset"
    assert tcp_gap("converted") < 1e-4, "with the tool offset, log and twin compare one point"
    bad = import_log(log, tmp_path / "bad", "--tcp-offset", "0 0 0.1")
    assert bad.returncode == 2 and "--tcp-offset needs 6 numbers" in bad.stderr
    assert not (tmp_path / "bad").exists()
