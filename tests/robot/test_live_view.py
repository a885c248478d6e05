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
    blob = preview(image).blob.as_arrow_array()[0].values.to_numpy()
    decoded = cv2.imdecode(blob, cv2.IMREAD_COLOR)[..., ::-1]  # back to RGB
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
