"""`twinrl view` draws the cell in 3D: the twin's shapes logged once, moved per step by
the logged joints, gripper opening and object poses, read back with Rerun's own reader."""

from dataclasses import replace

import mujoco
import numpy as np
import yaml
from rerun.experimental import RrdReader

from tests.conftest import record_demos
from tests.data.test_web_view import free_ports
from tests.sim.test_gap_diagnose import FOUR_JOINT_ARM
from tests.test_cli import twinrl
from twinrl_data import schema
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_sim.build import compile_scene
from twinrl_sim.cli.view import twin_cell
from twinrl_sim.tasks import make_task


def _chunks(path):
    """{entity path: [record batches]} of an .rrd file."""
    out = {}
    for chunk in RrdReader(path).store().stream().to_chunks():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches, name):
    return [row for b in batches if name in b.schema.names for row in b.column(name).to_pylist()]


def test_the_view_draws_the_cell_moved_by_the_logged_joints(tmp_path):
    record_demos(tmp_path, seed=3)  # one twin episode per region, both cameras
    saved = twinrl("view", "session#0", "session#1", "--save", "cell.rrd", cwd=tmp_path)
    assert saved.returncode == 0, saved.stderr
    chunks = _chunks(tmp_path / "cell.rrd")
    label = "twin_twin_demo_0"
    cell = f"/world/{label}/cell"
    # Static shapes: the arm's links, the gripper and its fingers, the table, the objects.
    for body in ("link1", "link3", "link6", "gripper_finger_left", "gripper_finger_right",
                 "table", "banana", "plate"):  # fmt: skip
        shapes = [p for p in chunks if p.startswith(f"{cell}/{body}/")]
        assert shapes, body
        assert all(b.num_rows == 1 for p in shapes for b in chunks[p])  # logged once
    # A link's logged pose is the forward kinematics of the logged joints.
    episode = read_episode(Session(tmp_path / "session").episode_paths()[0])
    state, names = episode.data[schema.STATE], episode.meta.names[schema.STATE]
    scene = compile_scene(make_task("pick_place").scene)
    model, data = scene.model, mujoco.MjData(scene.model)
    translations = np.array(_column(chunks[f"{cell}/link3"], "Transform3D:translation"))[:, 0]
    assert len(translations) == len(episode)
    for t in (0, len(episode) // 2, len(episode) - 1):
        for joint in scene.layout.arm_joints:
            data.qpos[model.joint(joint).qposadr[0]] = state[t, names.index(f"q.{joint}")]
        mujoco.mj_kinematics(model, data)
        assert np.allclose(translations[t], data.xpos[model.body("link3").id], atol=1e-5)
    # The fingers follow the logged opening: their frames close in one for one as it
    # opens wider (each finger's frame sits at the far side of its pad).
    left, right = (
        np.array(_column(chunks[f"{cell}/gripper_finger_{side}"], "Transform3D:translation"))[:, 0]
        for side in ("left", "right")
    )
    opening = state[:, names.index("gripper.opening")]
    gap = np.linalg.norm(left - right, axis=1)
    assert np.ptp(opening) > 0.01
    assert np.allclose(gap + opening, gap[0] + opening[0], atol=1e-4)
    # The banana is drawn where the episode logged it.
    banana = np.array(_column(chunks[f"{cell}/banana"], "Transform3D:translation"))[:, 0]
    env_names = episode.meta.names[schema.ENVIRONMENT_STATE]
    logged = episode.data[schema.ENVIRONMENT_STATE][:, env_names.index("banana.x") :][:, :3]
    assert np.allclose(banana, logged, atol=1e-5)
    # Each camera is a frustum at its mount, its images inside (logged there only): the
    # front camera on the world, the wrist camera on the flange, which the arm moves.
    for camera, body in (("front", "world"), ("wrist", "flange")):
        frustum = chunks[f"{cell}/{body}/{camera}"]
        assert _column(frustum, "Pinhole:image_from_camera")
        assert len(_column(frustum, "Image:buffer")) == len(episode)
        assert f"/cameras/{label}/{camera}" not in chunks
    assert len(_column(chunks[f"{cell}/flange"], "Transform3D:translation")) == len(episode)
    # The second episode's cell is a translucent ghost over the first.
    first = _column(chunks[f"{cell}/link3/0"], "Capsules3D:colors")[0][0]
    ghost = _column(chunks["/world/twin_twin_demo_1/cell/link3/0"], "Capsules3D:colors")[0][0]
    assert first & 0xFF == 255 and ghost & 0xFF < 128


def test_the_view_shows_what_the_robot_touches_as_the_twin_sees_the_logged_steps(tmp_path):
    record_demos(tmp_path, seed=3)
    saved = twinrl("view", "session#0", "--save", "touch.rrd", cwd=tmp_path)
    assert saved.returncode == 0, saved.stderr
    chunks = _chunks(tmp_path / "touch.rrd")
    label = "twin_twin_demo"
    names = {n for row in _column(chunks[f"/world/{label}/contacts"], "Points3D:labels")
             for n in (row or [])}  # fmt: skip
    assert {"gripper_finger_left / banana", "gripper_finger_right / banana"} <= names
    # Each finger touches the banana from about the close on, not before.
    episode = read_episode(Session(tmp_path / "session").episode_paths()[0], images=False)
    closed = np.flatnonzero(episode.data[schema.ACTION][:, -1] >= schema.GRIPPER_CLOSED)
    touching = np.array(
        _column(chunks[f"/signals/contacts/{label}/gripper_finger_left-banana"], "Scalars:scalars")
    )[:, 0]
    assert len(touching) == len(episode) and touching[0] == 0
    first = int(np.flatnonzero(touching)[0])
    assert closed[0] <= first <= closed[0] + 5
    # Nothing is drawn touching an object whose pose the episode does not log.
    hidden = replace(episode, meta=replace(episode.meta, names={
        **episode.meta.names, schema.ENVIRONMENT_STATE: []}))  # fmt: skip
    cell = twin_cell(hidden)
    assert not any(cell.contacts(row, None) for row in episode.data[schema.STATE])


def test_a_whole_episode_is_posed_as_step_by_step_with_a_lost_object_held_where_last_seen(
    tmp_path,
):
    """The saved view poses every step at once (:meth:`TwinCell.steps`); the live view
    step by step: both say the same, and a stretch where the object's pose was lost (a
    tracker's NaN rows) keeps it where it was last logged."""
    record_demos(tmp_path, seed=3)
    episode = read_episode(Session(tmp_path / "session").episode_paths()[0], images=False)
    states = episode.data[schema.STATE]
    environments = episode.data[schema.ENVIRONMENT_STATE].copy()
    banana = episode.meta.names[schema.ENVIRONMENT_STATE].index("banana.x")
    lost = slice(len(episode) // 2, len(episode) // 2 + 5)
    environments[lost, banana : banana + 7] = np.nan
    cell = twin_cell(episode)
    steps = cell.steps(states, environments)
    assert sum(map(len, steps.contacts)) > 0
    for t in range(len(episode)):
        poses = cell(states[t], environments[t])
        assert set(poses) == set(steps.poses)
        for body, (position, quat) in poses.items():
            assert np.allclose(steps.poses[body][0][t], position, atol=1e-9), (t, body)
            assert np.allclose(steps.poses[body][1][t], quat, atol=1e-9), (t, body)
        alone = [(c.label, c.distance) for c in cell.contacts(states[t], environments[t])]
        assert alone == [(c.label, c.distance) for c in steps.contacts[t]], t
    held = steps.poses["banana"][0][lost]
    assert np.allclose(held, environments[lost.start - 1, banana : banana + 3], atol=1e-9)


def test_episodes_of_no_built_in_twin_open_without_3d_and_say_why(tmp_path, capsys):
    record_demos(tmp_path, seed=3)
    episode = read_episode(Session(tmp_path / "session").episode_paths()[0], images=False)
    foreign = replace(episode, meta=replace(episode.meta, task="fold_towel", robot="so101"))
    assert twin_cell(foreign) is None
    printed = capsys.readouterr().out.strip().splitlines()
    assert len(printed) == 1 and "no cell in 3D" in printed[0] and "so101" in printed[0]
    no_joints = replace(episode, meta=replace(episode.meta, names={}))
    assert twin_cell(no_joints) is None
    assert "lacks joint positions" in capsys.readouterr().out


def test_view_replay_draws_the_twin_as_a_ghost_with_how_far_apart_they_are(tmp_path):
    record_demos(tmp_path, seed=4)
    saved = twinrl("view", "session#0", "--replay", "--save", "ghost.rrd", cwd=tmp_path)
    assert saved.returncode == 0, saved.stderr
    chunks = _chunks(tmp_path / "ghost.rrd")
    ghost = "/world/twin_replay/cell"
    assert f"{ghost}/link3/0" in chunks and f"{ghost}/banana/0" in chunks
    color = _column(chunks[f"{ghost}/link3/0"], "Capsules3D:colors")[0][0]
    assert color & 0xFF < 128  # translucent
    # A twin episode replayed in the same twin comes back where it was logged.
    episode = read_episode(Session(tmp_path / "session").episode_paths()[0], images=False)
    apart = np.array(_column(chunks["/signals/apart/q.elbow/twin_replay"], "Scalars:scalars"))
    tcp = np.array(_column(chunks["/signals/apart/tcp_mm/twin_replay"], "Scalars:scalars"))
    assert len(apart) == len(tcp) == len(episode)
    assert np.abs(apart).max() < 1e-4 and tcp.max() < 0.1
    # Bad input: one line, exit 2, nothing written.
    for args, message in (
        (("--replay", "--twin", "missing.yaml", "--save", "x.rrd"), "does not exist"),
        (("--replay", "--save", "ghost.rrd"), "already exists"),
    ):
        result = twinrl("view", "session#0", *args, cwd=tmp_path)
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.rrd").exists()


def test_a_cell_of_ones_own_is_drawn_from_its_scene_file(tmp_path):
    """A four-joint arm that is not a UR: `--twin` names its scene, and its links move."""
    (tmp_path / "arm.xml").write_text(FOUR_JOINT_ARM)
    cell = make_task("pick_place").scene.model_dump(mode="json")
    cell["name"] = "four_joint_cell"
    cell["robot"] = {
        "mjcf": "arm.xml",
        "joints": ["yaw", "shoulder", "elbow", "wrist"],
        "actuators": ["m_yaw", "m_shoulder", "m_elbow", "m_wrist"],
        "flange_body": "tool",
        "home_qpos": [0.0, -0.844, 1.604, -0.76],
    }
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell, sort_keys=False))
    recorded = twinrl("sim", "excite", "--twin", "cell.yaml", "--world", "twin", "--episodes",
                      "1", "--duration", "3", "--out", "measured", cwd=tmp_path)  # fmt: skip
    assert recorded.returncode == 0, recorded.stderr
    saved = twinrl("view", "measured#0", "--twin", "cell.yaml", "--save", "arm.rrd", cwd=tmp_path)
    assert saved.returncode == 0, saved.stderr
    chunks = _chunks(tmp_path / "arm.rrd")
    upper = [p for p in chunks if p.endswith("/cell/upper")]
    assert upper and any(p.endswith("/cell/upper/0") for p in chunks)
    moves = np.array(_column(chunks[upper[0]], "Transform3D:quaternion"))[:, 0]
    assert len(moves) > 10 and np.ptp(moves, axis=0).max() > 0.01  # the shoulder turns


def test_view_web_serves_the_viewer_on_loopback_only(tmp_path):
    import signal
    import socket
    import subprocess
    import sys
    import urllib.request

    import psutil

    record_demos(tmp_path, seed=3)
    web, grpc = free_ports()
    server = subprocess.Popen(
        [sys.executable, "-m", "twinrl_learn", "view", "session#0", "--web",
         "--web-port", str(web), "--grpc-port", str(grpc)],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # As a script's `twinrl view --web &` starts it; Ctrl-C must stop it all the same.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )  # fmt: skip
    try:
        line = server.stdout.readline()
        assert "open http://127.0.0.1:" in line, (line, server.stderr.read())
        url = line.split()[1]
        assert f"rerun%2Bhttp%3A//127.0.0.1%3A{grpc}/proxy" in url
        page = urllib.request.urlopen(url, timeout=10).read().decode()
        assert "Rerun" in page and "<html" in page.lower()
        with socket.socket() as probe:  # the recording server answers on loopback
            probe.settimeout(5)
            assert probe.connect_ex(("127.0.0.1", grpc)) == 0
        outside = [a for a in socket.gethostbyname_ex(socket.gethostname())[2]
                   if not a.startswith("127.")]  # fmt: skip
        for address in outside:  # and nowhere else
            with socket.socket() as probe:
                probe.settimeout(1)
                assert probe.connect_ex((address, grpc)) != 0
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=30)  # a hang guard: a loaded host stops slowly
        except subprocess.TimeoutExpired:
            # Not left running to load the tests after it: the viewer and its children.
            for process in [*psutil.Process(server.pid).children(recursive=True), server]:
                process.kill()
            raise
    with socket.socket() as probe:  # the viewer stopped with it
        assert probe.connect_ex(("127.0.0.1", grpc)) != 0
    refused = twinrl("view", "session#0", "--web", "--save", "x.rrd", cwd=tmp_path)
    assert refused.returncode == 2 and "choose one" in refused.stderr
    refused = twinrl("view", "session#0", "--bind", "0.0.0.0", cwd=tmp_path)
    assert refused.returncode == 2 and "add --web" in refused.stderr
