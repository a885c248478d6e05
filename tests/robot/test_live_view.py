"""The live view: camera previews as downscaled JPEG, each step logged off the control
loop's thread."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from twinrl_data.schema import STATE, WRENCH
from twinrl_robot.live_view import PREVIEW_WIDTH, LiveView, preview, preview_stride
from twinrl_robot.robot import Sent
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.tasks import make_task


def test_a_640x480_camera_is_previewed_as_a_320x240_jpeg_of_the_same_picture() -> None:
    image = np.zeros((480, 640, 3), np.uint8)
    image[:, 320:, 0] = 200  # the right half red
    shown = preview(image)
    blob = np.frombuffer(shown.jpeg, np.uint8)
    decoded = cv2.imdecode(blob, cv2.IMREAD_COLOR)[..., ::-1]  # back to RGB
    assert shown.width == 320  # the twin's outlines are drawn at the preview's size
    assert decoded.shape == (240, 320, 3)
    assert abs(int(decoded[120, 240, 0]) - 200) < 8 and decoded[120, 80].max() < 8
    assert blob.nbytes < image.nbytes / 50


def test_a_camera_no_wider_than_the_preview_is_sent_at_its_size() -> None:
    assert preview_stride(PREVIEW_WIDTH) == 1 and preview_stride(PREVIEW_WIDTH + 1) == 2


def test_the_steps_handed_to_the_view_are_logged_by_its_thread(tmp_path: Path) -> None:
    from rerun.experimental import RrdReader

    task = make_task("pick_place")
    names = Cell(compile_scene(task.scene)).contract_names()[STATE]
    view = LiveView(str(tmp_path / "live.rrd"), task, ("front",), names)
    observation = {STATE: np.zeros(len(names), np.float32),
                   "observation.images.front": np.zeros((480, 640, 3), np.uint8),
                   WRENCH: np.array([0.0, 0.0, -12.0, 0.1, 0.0, 0.0], np.float32)}  # fmt: skip
    sent = Sent(action=np.zeros(7, np.float32), joint_target=np.zeros(6, np.float32))
    for _ in range(3):
        view.step(observation, sent)
    view.close()  # logs what it was handed last before it returns
    chunks = list(RrdReader(tmp_path / "live.rrd").store().stream().to_chunks())
    entities = {c.entity_path for c in chunks}
    assert {"/cameras/front", "/signals/actions/0", "/world/cell/link3"} <= entities
    # the grasp and the force at the tool, where the cell measures it
    assert {"/signals/grasp/opening", "/signals/grasp/command", "/signals/force/z",
            "/world/tcp_force"} <= entities  # fmt: skip


def test_the_live_view_shows_what_the_robot_touches_and_the_object_in_hand(tmp_path: Path) -> None:
    """A pick-and-place episode played to the live view step by step: the fingers'
    contacts with the banana and the banana in hand show as they happen."""
    import time

    from rerun.experimental import RrdReader

    from twinrl_data.mcap_log import read_episode
    from twinrl_data.schema import ACTION, ENVIRONMENT_STATE
    from twinrl_data.session import Session
    from twinrl_robot.scripted import run_scripted_expert

    session = Session.create(tmp_path / "s")
    run_scripted_expert("pick_place", world="twin", episodes=1, session=session, seed=3)
    episode = read_episode(session.episode_paths()[0], images=False)
    names = episode.meta.names
    view = LiveView(str(tmp_path / "live.rrd"), make_task("pick_place"), (), names[STATE],
                    environment_names=names[ENVIRONMENT_STATE])  # fmt: skip
    for t in range(len(episode)):
        observation = {STATE: episode.data[STATE][t],
                       ENVIRONMENT_STATE: episode.data[ENVIRONMENT_STATE][t]}  # fmt: skip
        action = episode.data[ACTION][t]
        view.step(observation, Sent(action=action, joint_target=np.zeros(6, np.float32)))
        time.sleep(0.02)  # the view logs the newest step it has; let it log each
    view.close()
    labels: dict[str, set] = {}
    for chunk in RrdReader(tmp_path / "live.rrd").store().stream().to_chunks():
        batch = chunk.to_record_batch()
        wanted = chunk.entity_path in ("/world/contacts", "/world/in_hand")
        if wanted and "Points3D:labels" in batch.schema.names:
            rows = batch.column("Points3D:labels").to_pylist()
            labels.setdefault(chunk.entity_path, set()).update(
                n for row in rows for n in (row or [])
            )
    assert {"gripper_finger_left / banana", "gripper_finger_right / banana"} <= labels[
        "/world/contacts"
    ]
    assert labels["/world/in_hand"] == {"in hand"}


def test_a_viewer_that_stops_reading_holds_up_neither_the_steps_nor_the_close(caplog) -> None:
    """A gRPC peer that accepts and never reads blocks rerun's calls for good (rerun
    0.33); they run in the view's own process, so handing steps goes on and closing
    stops that process within its time, with a warning."""
    import socket
    import threading

    from twinrl_robot.live_view import CLOSE_TIMEOUT

    silent = socket.create_server(("127.0.0.1", 0))
    accepted: list[socket.socket] = []
    threading.Thread(target=lambda: accepted.append(silent.accept()[0]), daemon=True).start()
    task = make_task("pick_place")
    names = Cell(compile_scene(task.scene)).contract_names()[STATE]
    url = f"rerun+http://127.0.0.1:{silent.getsockname()[1]}/proxy"
    view = LiveView(url, task, ("front",), names)
    rng = np.random.default_rng(0)
    sent = Sent(action=np.zeros(7, np.float32), joint_target=np.zeros(6, np.float32))
    for _ in range(200):  # noise compresses badly: megabytes the peer never takes
        image = rng.integers(0, 255, (480, 640, 3), np.uint8)
        view.step(
            {STATE: np.zeros(len(names), np.float32), "observation.images.front": image}, sent
        )
    closing = threading.Thread(target=view.close, daemon=True)
    closing.start()
    closing.join(CLOSE_TIMEOUT + 30)
    assert not closing.is_alive(), "closing the view waited on the viewer"
    assert view._process.poll() is not None
    assert "did not finish within" in caplog.text
    silent.close()
