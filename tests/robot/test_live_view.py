"""The live view's camera previews: downscaled JPEG, not the full image every step."""

from __future__ import annotations

import cv2
import numpy as np

from twinrl_robot.live_view import PREVIEW_WIDTH, preview, preview_stride


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
