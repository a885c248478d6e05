"""Excitation episodes, and joint logs imported from CSV (UR RTDE and generic maps)."""

import numpy as np
import pytest

from tests.test_cli import twinrl
from twinrl_data import schema as contract
from twinrl_data.errors import DataWarning
from twinrl_data.importers import ColumnMap, import_csv
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_robot.excitation import ExcitationSettings, run_excitation, safe_trajectory
from twinrl_sim.build import compile_scene
from twinrl_sim.kinematics import TcpKinematics
from twinrl_sim.robots.ur5e import JOINT_SPEED_LIMIT
from twinrl_sim.tasks import make_task


@pytest.fixture(scope="module")
def plant_excitation(tmp_path_factory):
    session = Session.create(tmp_path_factory.mktemp("excite") / "session")
    paths = run_excitation("pick_place", world="plant", episodes=2, session=session, seed=3)
    return [read_episode(p) for p in paths]


def test_excitation_stays_inside_the_workspace_and_speed_limit(rng):
    task = make_task("pick_place")
    scene = compile_scene(task.scene)
    settings = ExcitationSettings(amplitude=2.0)  # too big: must be scaled down
    targets = safe_trajectory(task, settings, rng, scene)
    fk = TcpKinematics(scene)
    tcp = np.array([fk(q)[0] for q in targets])
    low = np.array(task.scene.workspace.low) + settings.margin
    high = np.array(task.scene.workspace.high) - settings.margin
    assert (tcp[:, :2] >= low[:2]).all() and (tcp <= high).all() and (tcp[:, 2] > 0.05).all()
    rate = task.scene.physics.control_hz
    assert np.abs(np.diff(targets, axis=0)).max() * rate <= 0.5 * JOINT_SPEED_LIMIT
    home = np.asarray(scene.layout.home_qpos)
    np.testing.assert_allclose(targets[0], home, atol=1e-9)  # starts and ends at rest
    np.testing.assert_allclose(targets[-1], home, atol=1e-9)
    assert np.ptp(targets, axis=0).min() > 0.05  # every joint moves


def test_excitation_episodes_follow_the_contract(plant_excitation):
    episode = plant_excitation[0]
    meta = episode.meta
    assert meta.source == "excitation" and meta.world == "plant" and len(episode) == 100
    assert episode.data[contract.EFFORT].shape == (100, 6)
    assert meta.names[contract.EFFORT][0] == "tau.shoulder_pan"
    q = episode.data[contract.STATE][:, :6]
    targets = episode.data[contract.JOINT_TARGET]
    assert np.abs(q[1:] - targets[:-1]).max() < 0.1  # the servos follow the targets
    assert np.abs(episode.data[contract.EFFORT]).max() > 1.0  # gravity and motion torques
    assert not np.allclose(
        plant_excitation[0].data[contract.JOINT_TARGET],
        plant_excitation[1].data[contract.JOINT_TARGET],
    )


def write_rtde(path, episode, delimiter=" "):
    """The episode as UR's RTDE recorder writes it (125 Hz would be typical; 10 Hz here)."""
    state, target = episode.data[contract.STATE], episode.data[contract.JOINT_TARGET]
    quat = state[:, 15:19].astype(float)
    angle = 2 * np.arccos(np.clip(quat[:, :1], -1, 1))
    axis = quat[:, 1:] / np.maximum(np.sin(angle / 2), 1e-12)
    header = (
        ["timestamp"]
        + [f"target_q_{i}" for i in range(6)]
        + [f"actual_q_{i}" for i in range(6)]
        + [f"actual_qd_{i}" for i in range(6)]
        + [f"actual_current_{i}" for i in range(6)]
        + [f"target_moment_{i}" for i in range(6)]
        + [f"actual_TCP_pose_{i}" for i in range(6)]
    )
    t = 1700000000.0 + np.arange(len(episode)) / episode.meta.fps
    rows = np.column_stack(
        [
            t,
            target,
            state[:, :6],
            state[:, 6:12],
            np.zeros((len(t), 6)),
            episode.data[contract.EFFORT],
            state[:, 12:15],
            axis * angle,
        ]
    )
    lines = [delimiter.join(header)] + [delimiter.join(f"{v:.9f}" for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")


def test_rtde_csv_round_trip(tmp_path, plant_excitation):
    episode = plant_excitation[0]
    csv_path = tmp_path / "rtde.csv"
    write_rtde(csv_path, episode)
    imported = import_csv(csv_path)
    assert imported.meta.source == "imported" and imported.meta.fps == pytest.approx(10.0)
    assert len(imported) == len(episode)
    np.testing.assert_allclose(
        imported.data[contract.STATE][:, :12], episode.data[contract.STATE][:, :12], atol=1e-6
    )
    np.testing.assert_allclose(
        imported.data[contract.STATE][:, 12:15], episode.data[contract.STATE][:, 12:15], atol=1e-6
    )
    quat_in, quat_out = (
        episode.data[contract.STATE][:, 15:19],
        imported.data[contract.STATE][:, 15:19],
    )
    assert np.abs(np.abs((quat_in * quat_out).sum(1)) - 1).max() < 1e-5  # same rotation
    np.testing.assert_allclose(
        imported.data[contract.JOINT_TARGET], episode.data[contract.JOINT_TARGET], atol=1e-6
    )
    np.testing.assert_allclose(
        imported.data[contract.EFFORT], episode.data[contract.EFFORT], atol=1e-4
    )
    moves = imported.data[contract.ACTION][:-1, :3]
    np.testing.assert_allclose(
        moves, np.diff(episode.data[contract.STATE][:, 12:15], axis=0), atol=1e-6
    )
    with pytest.warns(DataWarning, match="from 10 Hz to 5 Hz"):
        half = import_csv(csv_path, fps=5.0)  # resampled onto a slower clock
    assert len(half) == 50 and half.meta.fps == 5.0


def _import_generic(folder, out, *options: str):
    """``twinrl data import-csv`` of ``folder/log.csv`` with the map ``folder/map.yaml``."""
    return twinrl(
        "data",
        "import-csv",
        str(folder / "log.csv"),
        "--format",
        "generic",
        "--map",
        str(folder / "map.yaml"),
        *options,
        "--out",
        str(out),
    )


def test_generic_long_csv_in_degrees_and_ms(tmp_path, plant_excitation):
    episode = plant_excitation[1]
    q = episode.data[contract.STATE][:, :6].astype(float)
    target = episode.data[contract.JOINT_TARGET].astype(float)
    lines = ["t_ms;name;val"]
    for k in range(len(episode)):
        for j in range(6):
            lines.append(f"{k * 100};cmd{j};{np.degrees(target[k, j]):.9f}")
            lines.append(f"{k * 100 + 3};pos{j};{np.degrees(q[k, j]):.9f}")
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "map.yaml").write_text(
        "time: t_ms\ntime_unit: ms\nangle_unit: deg\nlayout: long\nsignal_column: name\n"
        "value_column: val\ncommanded: [cmd0, cmd1, cmd2, cmd3, cmd4, cmd5]\n"
        "measured: [pos0, pos1, pos2, pos3, pos4, pos5]\n"
    )
    out = tmp_path / "imported"
    result = _import_generic(tmp_path, out, "--fps", "10")
    assert result.returncode == 0, result.stderr
    imported = read_episode(Session(out).episode_paths()[0])
    names = imported.meta.names[contract.STATE]
    assert names[:6] == [
        f"q.{j}" for j in ColumnMap(time="t", commanded=["a"] * 6, measured=["b"] * 6).joints
    ]
    assert "tcp.x" in names and "qd.elbow" not in names  # TCP from the twin's kinematics
    np.testing.assert_allclose(imported.data[contract.JOINT_TARGET][:-1], target[:-1], atol=1e-3)
    fk_tcp = imported.data[contract.STATE][:, 6:9]
    np.testing.assert_allclose(fk_tcp[:-1], episode.data[contract.STATE][:-1, 12:15], atol=5e-3)


@pytest.mark.parametrize(
    ("map_text", "message"),
    [
        ("time: t\ncommanded: [a, b]\nmeasured: [c, d]\n", "commanded needs 6 columns"),
        (
            "time: t\ntime_unit: min\ncommanded: [a,b,c,d,e,f]\nmeasured: [a,b,c,d,e,f]\n",
            "time_unit must be one of",
        ),
        (
            "time: t\ncommanded: [a,b,c,d,e,f]\nmeasured: [a,b,c,d,e,f]\ncolour: red\n",
            "unknown key(s) ['colour']",
        ),
        ("time: nope\ncommanded: [a,b,c,d,e,f]\nmeasured: [a,b,c,d,e,f]\n", "column(s) ['nope']"),
    ],
)
def test_bad_column_maps_give_one_line(tmp_path, map_text, message):
    (tmp_path / "log.csv").write_text("t,a,b,c,d,e,f\n0,0,0,0,0,0,0\n0.1,0,0,0,0,0,0\n")
    (tmp_path / "map.yaml").write_text(map_text)
    out = tmp_path / "out"
    result = _import_generic(tmp_path, out)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and not out.exists()


def test_excite_cli_refuses_to_overwrite(tmp_path):
    out = tmp_path / "exc"
    first = twinrl("sim", "excite", "--out", str(out), "--episodes", "1", "--duration", "3")
    assert first.returncode == 0, first.stderr
    before = sorted(p.name for p in (out / "episodes").iterdir())
    again = twinrl("sim", "excite", "--out", str(out), "--episodes", "1")
    assert again.returncode == 2 and "not empty" in again.stderr
    assert sorted(p.name for p in (out / "episodes").iterdir()) == before
    bad = twinrl("sim", "excite", "--out", str(tmp_path / "x"), "--world", "mars")
    assert bad.returncode == 2 and "--world must be twin or plant" in bad.stderr
    wrong_cell = twinrl(
        "sim",
        "excite",
        "--out",
        str(tmp_path / "y"),
        "--task",
        "insert_hexagon",
        "--twin",
        "pick_place",
    )  # a cell without the task's objects
    assert wrong_cell.returncode == 2 and "pick the --task it is built for" in wrong_cell.stderr
    assert not (tmp_path / "y").exists()
