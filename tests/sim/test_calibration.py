"""The filming camera's intrinsics: ``twinrl twin calibrate`` on a clip of a printed
board seen through a distorting lens, calibration files (OpenCV, COLMAP) read and
scaled, and an EXIF focal length as a prior."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from PIL import Image

from tests.test_cli import twinrl
from twinrl_data.errors import SettingError
from twinrl_sim.reconstruct.calibration import (
    Calibration,
    board_image,
    calibrate,
    exif_focal,
    filming_camera,
    read_calibration,
    write_calibration,
)
from twinrl_sim.reconstruct.camera_traits import CameraTraits, TraitApplier, camera_matrix
from twinrl_sim.reconstruct.frames import CaptureError
from twinrl_sim.reconstruct.settings import Board

SIZE = (640, 480)
LENS = (560.0, 565.0, 322.0, 236.0, 0.11, -0.21, 0.0012, -0.0008)
PIXELS_PER_SQUARE = 60


def _board_origin_px(board: Board) -> float:
    """Board pixel of the board's (0, 0) point: its first inner corner (checkerboard)
    or its outer corner (ChArUco), one square of margin either way."""
    return (2 if board.board == "checkerboard" else 1) * PIXELS_PER_SQUARE


def film_board(board: Board, folder, views: int = 24, seed: int = 0) -> None:
    """Frames of ``board`` held at varied poses before a camera with :data:`LENS`."""
    rng = np.random.default_rng(seed)
    image = board_image(board, PIXELS_PER_SQUARE)
    to_pixels = PIXELS_PER_SQUARE / board.square_size
    metres_to_board = np.array(
        [
            [to_pixels, 0, _board_origin_px(board)],
            [0, to_pixels, _board_origin_px(board)],
            [0, 0, 1],
        ]
    )
    columns, rows = board.squares
    centre = np.array([columns, rows, 0.0]) * board.square_size / 2
    apply = TraitApplier(CameraTraits(distortion=LENS[4:], noise=2.0), LENS[:4], SIZE, views, rng)
    folder.mkdir(parents=True, exist_ok=True)
    for view in range(views):
        tilt = rng.uniform(-0.5, 0.5, 3) * [1, 1, 0.6]
        rotation, _ = cv2.Rodrigues(tilt)
        offset = np.r_[rng.uniform(-0.06, 0.06, 2), rng.uniform(0.28, 0.42)]
        translation = offset - rotation @ centre
        board_to_image = camera_matrix(LENS[:4]) @ np.c_[rotation[:, :2], translation]
        warp = board_to_image @ np.linalg.inv(metres_to_board)
        frame = cv2.warpPerspective(image, warp, SIZE, borderValue=110)
        frame = apply(np.repeat(frame[:, :, None], 3, axis=2), view)
        cv2.imwrite(str(folder / f"board_{view:03d}.png"), frame)


@pytest.mark.parametrize(
    "board",
    [Board(), Board(board="charuco", squares=(7, 5), square_size=0.03, marker_size=0.022)],
    ids=["checkerboard", "charuco"],
)
def test_a_board_clip_gives_the_lens_back(board, tmp_path):
    film_board(board, tmp_path / "clip")
    solved = calibrate(tmp_path / "clip", board)
    assert solved.size == SIZE and solved.views >= 16 and solved.rms_px < 0.5
    fx, fy, cx, cy, k1, *_ = solved.intrinsics
    assert abs(fx / LENS[0] - 1) < 0.01 and abs(fy / LENS[1] - 1) < 0.01
    assert abs(cx - LENS[2]) < 3 and abs(cy - LENS[3]) < 3
    assert abs(k1 - LENS[4]) < 0.03
    # What matters: a point well off centre lands where the true lens puts it.
    ray = np.array([[0.3, 0.2, 1.0]])
    expected, _ = cv2.projectPoints(
        ray, np.zeros(3), np.zeros(3), camera_matrix(LENS), np.array(LENS[4:])
    )
    found, _ = cv2.projectPoints(
        ray,
        np.zeros(3),
        np.zeros(3),
        camera_matrix(solved.intrinsics),
        np.array(solved.intrinsics[4:]),
    )
    assert np.linalg.norm(found - expected) < 1.5


def test_twin_calibrate_writes_a_file_twin_build_reads(tmp_path):
    film_board(Board(), tmp_path / "clip")
    out = tmp_path / "phone.yaml"
    result = twinrl("twin", "calibrate", str(tmp_path / "clip"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "reprojection" in result.stdout and out.is_file()
    intrinsics = read_calibration(out, SIZE)
    assert abs(intrinsics[0] / LENS[0] - 1) < 0.01
    # Not written twice, and a clip without the board says what to check.
    again = twinrl("twin", "calibrate", str(tmp_path / "clip"), "--out", str(out))
    assert again.returncode != 0 and "exists" in again.stderr and "--out" in again.stderr
    wrong = twinrl(
        "twin",
        "calibrate",
        str(tmp_path / "clip"),
        "--squares",
        "7x4",
        "--out",
        str(tmp_path / "x.yaml"),
    )
    assert wrong.returncode != 0 and re.search(r"found in \d of 24 frames", wrong.stderr)
    assert "--squares" in wrong.stderr and not (tmp_path / "x.yaml").exists()


def test_calibration_files_are_read_and_scaled_to_the_frames(tmp_path):
    solved = Calibration(LENS, (1280, 960), 0.2, 30, 30)
    path = write_calibration(solved, tmp_path / "phone.yaml")
    assert read_calibration(path, (1280, 960)) == pytest.approx(LENS)
    half = read_calibration(path, (640, 480))  # filmed at half the resolution
    assert half[:2] == pytest.approx((LENS[0] / 2, LENS[1] / 2))
    assert half[2:4] == pytest.approx(((LENS[2] + 0.5) / 2 - 0.5, (LENS[3] + 0.5) / 2 - 0.5))
    assert half[4:] == pytest.approx(LENS[4:])
    with pytest.raises(SettingError, match="another aspect"):
        read_calibration(path, (640, 360))
    colmap = tmp_path / "cameras.txt"
    colmap.write_text("# Camera list\n1 OPENCV 640 480 " + " ".join(map(str, LENS)) + "\n")
    assert read_calibration(colmap, SIZE) == pytest.approx(LENS)
    colmap.write_text("1 SIMPLE_RADIAL 640 480 550 320 240 0.05\n")
    assert read_calibration(colmap, SIZE) == pytest.approx((550, 550, 320, 240, 0.05, 0, 0, 0))
    colmap.write_text("1 FISHEYE 640 480 1 2 3 4\n")
    with pytest.raises(SettingError, match="'FISHEYE' is not one of"):
        read_calibration(colmap, SIZE)
    ros = tmp_path / "ost.yaml"  # as ROS's camera_calibration writes it
    ros.write_text(
        "image_width: 640\nimage_height: 480\ncamera_name: phone\n"
        "camera_matrix: {rows: 3, cols: 3, data: [560, 0, 322, 0, 565, 236, 0, 0, 1]}\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [0.11, -0.21, 0.0012, -0.0008, 0]}\n"
    )
    assert read_calibration(ros, SIZE) == pytest.approx(LENS)
    junk = tmp_path / "junk.yaml"
    junk.write_text("just: words\n")
    with pytest.raises(SettingError, match="no 3x3 `camera_matrix`"):
        read_calibration(junk, SIZE)


def test_a_board_never_seen_is_named(tmp_path):
    blank = tmp_path / "blank"
    blank.mkdir()
    rng = np.random.default_rng(0)
    for k in range(10):
        cv2.imwrite(str(blank / f"{k}.png"), rng.integers(0, 255, (480, 640, 3), dtype=np.uint8))
    with pytest.raises(CaptureError, match="found in 0 of 10 frames"):
        calibrate(blank, Board())
    with pytest.raises(SettingError, match="'dots' is not one of"):
        calibrate(blank, Board(board="dots"))


def test_an_exif_focal_length_is_a_prior_and_known_intrinsics_win(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    picture = Image.fromarray(np.zeros((480, 640, 3), np.uint8))
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 26  # a phone's main camera: 26 mm equivalent
    picture.save(frames / "a.jpg", exif=exif)
    focal = exif_focal(frames / "a.jpg")
    assert focal == pytest.approx(26 / 36 * 640)
    camera = filming_camera(frames, frames / "a.jpg", None, None)
    assert camera.intrinsics is None and camera.focal_prior == pytest.approx(focal)
    assert "EXIF" in camera.describe()
    given = filming_camera(frames, frames / "a.jpg", LENS[:4], None)
    assert given.intrinsics == LENS[:4] and given.focal_prior is None
    Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(tmp_path / "plain.jpg")
    assert exif_focal(tmp_path / "plain.jpg") is None
