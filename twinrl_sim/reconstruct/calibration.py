"""The filming camera's intrinsics: estimated from a clip of a printed board, read from
a calibration file, or taken as a prior from the frames' EXIF.

Structure from motion on a narrow hand-held sweep cannot tell a phone's focal length
from its distance, nor follow its lens's distortion with one coefficient; a table 1.4 m
long came out 8 % too long. Known intrinsics fix both.

- :func:`calibrate` finds a checkerboard or ChArUco board (OpenCV) in a clip's frames,
  keeps well-spread sharp views and solves OpenCV's pinhole + ``k1 k2 p1 p2`` model.
- :func:`write_calibration` and :func:`read_calibration` use OpenCV's own file format
  (``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``),
  which OpenCV's tools and most ROS camera drivers read and write; a COLMAP
  ``cameras.txt`` is read as well. Intrinsics are scaled to the clip's frame size when
  the calibration was made at another resolution of the same aspect.
- :func:`exif_focal` reads a 35 mm-equivalent focal length from the first frame's EXIF,
  a prior that structure from motion still refines.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from PIL import Image

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_sim.reconstruct.frames import CaptureError, sharpness, stream_frames
from twinrl_sim.reconstruct.settings import BOARDS, Board

MAX_VIEWS = 40  # views solved with, spread over the clip (more only slow the solve)
MIN_VIEWS = 8
MIN_SHARPNESS = 30.0
# COLMAP camera models -> how their parameters map to fx fy cx cy k1 k2 p1 p2.
COLMAP_MODELS: dict[str, Callable[[list[float]], tuple[float, ...]]] = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2]),
    "PINHOLE": lambda p: tuple(p[:4]),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], p[4], 0.0, 0.0),
    "OPENCV": lambda p: tuple(p[:8]),
}


@dataclass(frozen=True)
class Calibration:
    """A solved camera: intrinsics in pixels of ``size`` (width, height)."""

    intrinsics: tuple[float, ...]  # fx fy cx cy k1 k2 p1 p2
    size: tuple[int, int]
    rms_px: float  # RMS reprojection error of the board's corners
    views: int  # views solved with
    frames: int  # frames read


def _detector(board: Board) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None]:
    """A function from a grey image to (object points, image points) of the board's
    corners it finds, or None."""
    columns, rows = board.squares
    if board.board == "checkerboard":
        grid = np.zeros((rows * columns, 3), np.float32)
        grid[:, :2] = np.mgrid[0:columns, 0:rows].T.reshape(-1, 2) * board.square_size

        def find_checkerboard(grey: np.ndarray):
            found, corners = cv2.findChessboardCornersSB(grey, (columns, rows))
            return (grid, corners.reshape(-1, 2)) if found else None

        return find_checkerboard
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    charuco = cv2.aruco.CharucoBoard(
        (columns, rows), board.square_size, board.marker_size, dictionary
    )
    detector = cv2.aruco.CharucoDetector(charuco)

    def find_charuco(grey: np.ndarray):
        corners, ids, _, _ = detector.detectBoard(grey)
        if ids is None or len(ids) < 6:
            return None
        objects, image = charuco.matchImagePoints(corners, ids)
        return objects.reshape(-1, 3), image.reshape(-1, 2)

    return find_charuco


def board_image(board: Board, pixels_per_square: int = 80) -> np.ndarray:
    """The board to print (grey, white margin of one square), as OpenCV draws it."""
    columns, rows = board.squares
    if board.board == "checkerboard":  # ``squares`` counts inner corners
        cells = np.indices((rows + 1, columns + 1)).sum(axis=0) % 2
        image = np.kron(1 - cells, np.ones((pixels_per_square, pixels_per_square)))
        image = (255 * image).astype(np.uint8)
        return cv2.copyMakeBorder(image, *[pixels_per_square] * 4, cv2.BORDER_CONSTANT, 255)
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    charuco = cv2.aruco.CharucoBoard(
        (columns, rows), board.square_size, board.marker_size, dictionary
    )
    size = ((columns + 2) * pixels_per_square, (rows + 2) * pixels_per_square)
    return charuco.generateImage(size, marginSize=pixels_per_square)


def calibrate(
    source: str | Path,
    board: Board | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> Calibration:
    """Solve the camera that filmed ``board`` in ``source`` (a video or image folder).

    Every sharp frame is searched; of those where the board is found, up to
    :data:`MAX_VIEWS` spread over the clip are solved with (``cv2.calibrateCamera``,
    pinhole with ``k1 k2 p1 p2``)."""
    source, board = Path(source), board or Board()
    if board.board not in BOARDS:
        raise SettingError("board", f"'{board.board}' is not one of {', '.join(BOARDS)}")
    if board.board == "charuco" and not hasattr(cv2.aruco, board.dictionary):
        raise SettingError("dictionary", f"'{board.dictionary}' is not an OpenCV ArUco dictionary")
    find = _detector(board)
    found: list[tuple[np.ndarray, np.ndarray]] = []
    size, frames = None, 0
    for frame in stream_frames(source):
        frames += 1
        if on_frame is not None:
            on_frame(frames)
        grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        size = size or (grey.shape[1], grey.shape[0])
        if (grey.shape[1], grey.shape[0]) != size or sharpness(grey) < MIN_SHARPNESS:
            continue
        corners = find(grey)
        if corners is not None:
            found.append(corners)
    if len(found) < MIN_VIEWS:
        raise CaptureError(
            f"the {board.board} board ({board.squares[0]}x{board.squares[1]}) was found in "
            f"{len(found)} of {frames} frames, {MIN_VIEWS} needed; check `squares` "
            "(inner corners of a checkerboard, squares of a ChArUco board), film it whole "
            "from several angles, slowly"
        )
    chosen = [
        found[i]
        for i in np.linspace(0, len(found) - 1, min(MAX_VIEWS, len(found))).round().astype(int)
    ]
    objects = [o.astype(np.float32) for o, _ in chosen]
    images = [i.astype(np.float32) for _, i in chosen]
    rms, matrix, distortion, _, _ = cv2.calibrateCamera(objects, images, size, None, None)
    fx, fy, cx, cy = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
    k1, k2, p1, p2 = distortion.ravel()[:4]
    intrinsics = tuple(float(v) for v in (fx, fy, cx, cy, k1, k2, p1, p2))
    return Calibration(intrinsics, size, float(rms), len(chosen), frames)


def check_new_file(path: Path) -> None:
    """Refuse to write over an existing calibration file."""
    if Path(path).exists():
        raise SettingError("out", f"{path} exists; give another file or remove it first")


def write_calibration(calibration: Calibration, path: str | Path) -> Path:
    """Write ``calibration`` in OpenCV's YAML format (atomically); an existing file is
    refused, not overwritten."""
    path = Path(path)
    check_new_file(path)
    storage = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fx, fy, cx, cy, *distortion = calibration.intrinsics
    storage.write("image_width", calibration.size[0])
    storage.write("image_height", calibration.size[1])
    storage.write("camera_matrix", np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], float))
    storage.write("distortion_coefficients", np.array(distortion, float).reshape(1, -1))
    storage.write("reprojection_error_px", calibration.rms_px)
    storage.write("views", calibration.views)
    write_text_atomic(path, storage.releaseAndGetString())
    return path


def read_calibration(path: str | Path, frame_size: tuple[int, int]) -> tuple[float, ...]:
    """fx fy cx cy k1 k2 p1 p2 from an OpenCV calibration file (YAML, XML or JSON) or a
    COLMAP ``cameras.txt``, in pixels of frames of ``frame_size`` (width, height)."""
    path = Path(path)
    if not path.is_file():
        raise SettingError("calibration", f"{path} is not a file")
    if path.suffix.lower() == ".txt":
        intrinsics, size = _read_colmap(path)
    else:
        intrinsics, size = _read_opencv(path)
    return _scaled(intrinsics, size, frame_size, path)


def _read_opencv(path: Path) -> tuple[tuple[float, ...], tuple[int, int] | None]:
    """OpenCV's FileStorage format (``%YAML:1.0``, XML, JSON) or plain YAML as ROS's
    camera calibration writes it (``camera_matrix: {rows, cols, data}``)."""
    fields = _opencv_fields(path) or _plain_yaml_fields(path)
    matrix = next((fields[k] for k in ("camera_matrix", "cameraMatrix", "K") if k in fields), None)
    if matrix is None or np.size(matrix) != 9:
        raise SettingError("calibration", f"{path} has no 3x3 `camera_matrix`")
    matrix = np.reshape(np.asarray(matrix, float), (3, 3))
    keys = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
    distortion = next((fields[k] for k in keys if k in fields), None)
    coefficients = np.zeros(4) if distortion is None else np.ravel(distortion)[:4].astype(float)
    coefficients = np.r_[coefficients, np.zeros(4 - len(coefficients))]
    size = None
    if "image_width" in fields and "image_height" in fields:
        size = (int(fields["image_width"]), int(fields["image_height"]))
    intrinsics = (matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2], *coefficients)
    return tuple(float(v) for v in intrinsics), size


def _opencv_fields(path: Path) -> dict[str, object]:
    """The calibration's fields from an OpenCV FileStorage file; {} if it is not one."""
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV raises these on a file not its own
        return {}
    fields: dict[str, object] = {}
    if storage.isOpened():
        names = storage.root().keys()  # a FileNode's, not a dict's
        for key in names:
            node = storage.getNode(key)
            fields[key] = node.mat() if node.isMap() or node.isSeq() else node.real()
        storage.release()
    return {k: v for k, v in fields.items() if v is not None}


def _plain_yaml_fields(path: Path) -> dict[str, object]:
    """The calibration's fields from plain YAML; matrices as ``{data: [...]}`` or lists."""
    try:
        loaded = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError):
        raise SettingError("calibration", f"{path} is neither OpenCV's format nor YAML") from None
    if not isinstance(loaded, dict):
        return {}
    return {
        key: value["data"] if isinstance(value, dict) and "data" in value else value
        for key, value in loaded.items()
    }


def _read_colmap(path: Path) -> tuple[tuple[float, ...], tuple[int, int]]:
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        fields = line.split()
        model = fields[1] if len(fields) > 4 else ""
        if model not in COLMAP_MODELS:
            raise SettingError(
                "calibration",
                f"{path}: COLMAP camera model '{model}' is not one of {', '.join(COLMAP_MODELS)}",
            )
        params = [float(v) for v in fields[4:]]
        return COLMAP_MODELS[model](params), (int(fields[2]), int(fields[3]))
    raise SettingError("calibration", f"{path} lists no camera (COLMAP cameras.txt)")


def _scaled(
    intrinsics: tuple[float, ...],
    size: tuple[int, int] | None,
    frame_size: tuple[int, int],
    path: Path,
) -> tuple[float, ...]:
    """``intrinsics`` for frames of ``frame_size``, when calibrated at ``size``."""
    if size is None or size == frame_size:
        return intrinsics
    scale_x, scale_y = frame_size[0] / size[0], frame_size[1] / size[1]
    if abs(scale_x - scale_y) > 0.01 * scale_x:
        raise SettingError(
            "calibration",
            f"{path} is for {size[0]}x{size[1]} images, the frames are "
            f"{frame_size[0]}x{frame_size[1]} (another aspect: another crop); calibrate "
            "at the resolution you film",
        )
    fx, fy, cx, cy, *rest = intrinsics
    # Pixel centres: a pixel's centre is at +0.5, so the scaling is about -0.5.
    cx, cy = (cx + 0.5) * scale_x - 0.5, (cy + 0.5) * scale_y - 0.5
    return (fx * scale_x, fy * scale_y, cx, cy, *rest)


def exif_focal(image: Path) -> float | None:
    """The focal length in pixels that ``image``'s EXIF 35 mm-equivalent focal length
    gives (36 mm across the long side), or None when it carries none."""
    try:
        with Image.open(image) as picture:
            details = picture.getexif().get_ifd(0x8769)  # the Exif sub-IFD
            equivalent = details.get(0xA405)  # FocalLengthIn35mmFilm
            long_side = max(picture.size)
    except OSError:
        return None
    if not equivalent:
        return None
    return float(equivalent) / 36.0 * long_side


@dataclass(frozen=True)
class FilmingCamera:
    """What is known of the camera that filmed the walk before it is mapped."""

    intrinsics: tuple[float, ...] | None  # held fixed (given, or from a calibration file)
    focal_prior: float | None  # px, from EXIF: a first guess the mapper refines
    origin: str  # "given", "calibration FILE", "exif" or "estimated"

    def describe(self) -> list[float] | str:
        """For the scene's provenance."""
        if self.intrinsics is not None and self.origin == "given":
            return list(self.intrinsics)
        if self.intrinsics is not None:
            return f"{self.origin}: {' '.join(f'{v:.6g}' for v in self.intrinsics)}"
        if self.focal_prior is not None:
            return f"estimated from EXIF focal length {self.focal_prior:.1f} px"
        return "estimated"


def filming_camera(
    source: Path,
    first_frame: Path,
    intrinsics: tuple[float, ...] | None,
    calibration: Path | None,
) -> FilmingCamera:
    """The walk's intrinsics as given, from the ``calibration`` file (scaled to the size
    of ``first_frame``), or else a focal length prior from the first source image's
    EXIF (a video's frames carry none)."""
    if intrinsics is not None:
        return FilmingCamera(tuple(intrinsics), None, "given")
    if calibration is not None:
        height, width = cv2.imread(str(first_frame)).shape[:2]
        known = read_calibration(calibration, (width, height))
        return FilmingCamera(known, None, f"calibration {Path(calibration).name}")
    if Path(source).is_dir():
        images = sorted(p for p in Path(source).iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
        focal = exif_focal(images[0]) if images else None
        if focal is not None:
            return FilmingCamera(None, focal, "exif")
    return FilmingCamera(None, None, "estimated")
