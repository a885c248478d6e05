"""What a twin build is told besides the clip, and its stages: light to import, so that
the command line derives its options from it without loading the reconstruction."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

STAGES = (
    "frames",
    "structure from motion",
    "alignment",
    "table",
    "objects",
    "cameras",
    "look",
    "scene",
    "report",
)


@dataclass(frozen=True)
class BuildSettings:
    """What ``twinrl twin build`` is told besides the clip.

    The robot-base frame comes from either ``tag_pose``, one tag's centre and orientation
    in the base frame (x y z qw qx qy qz), with ``tag_size``, the edge of its black
    square (m); or ``tag_points``, the base-frame centres of 3+ tags by id.
    """

    tag_size: float | None = None
    """Edge of the tag's black square (m), e.g. 0.08."""
    tag_pose: tuple[float, ...] | None = None
    """The tag's centre and orientation in the robot-base frame: 'x y z qw qx qy qz' (m;
    a tag lying flat, printed x along the base's x: 'x y z 1 0 0 0'). Needs the tag size."""
    tag_id: int | None = None
    """The tag the tag pose measures (default: the only one seen)."""
    tag_points: dict[int, tuple[float, ...]] = field(default_factory=dict)
    """ID=x,y,z: the centre of tag ID in the robot-base frame (m), instead of a tag pose;
    3 or more tags, not on one line. Repeatable."""
    tag_family: str = "tag36h11"
    """The printed markers' family: tag36h11, tag36h10, tag25h9, tag16h5 (AprilTag),
    aruco4x4, aruco5x5, aruco6x6, aruco7x7, aruco_original (ArUco)."""
    tags_on_table: bool = True
    """The tags lie on the table: its plane is sought near the tags' plane only, and one
    tilted from it is refused (--no-tags-on-table: the largest plane in view)."""
    workspace: tuple[float, ...] | None = None
    """A box around the table in the robot-base frame, 'x_min y_min z_min x_max y_max
    z_max' (m): points outside it (the room behind, the floor) are cut before the table
    and objects are fitted (default: all points)."""
    task: str | None = None
    """Task whose cell was filmed: objects are named after its objects, and its robot,
    cameras and physics are kept."""
    object_meshes: dict[str, Path] = field(default_factory=dict)
    """NAME=FILE: a scan or CAD mesh (metres) of object NAME, registered to its points by
    ICP instead of the reconstructed shape. Repeatable."""
    camera_images: dict[str, Path] = field(default_factory=dict)
    """NAME=IMAGE: a photo from fixed camera NAME (e.g. front=front.png); the twin's
    camera is placed at its pose with its focal length. Repeatable."""
    densities: dict[str, float] = field(default_factory=dict)
    """NAME=KG_PER_M3 for an object's mass (default 700). Repeatable."""
    intrinsics: tuple[float, ...] | None = None
    """The filming camera's intrinsics, when known: 'fx fy cx cy' in pixels of the clip's
    frames, optionally followed by OpenCV's distortion 'k1 k2 p1 p2'; held fixed while
    the walk is mapped (default: estimated from the frames)."""
    refine_distortion: bool = False
    """With known `intrinsics` or a `calibration`: estimate the lens distortion (k1 k2 p1
    p2) while mapping, the focal length and principal point held; for a calibration
    that gives no distortion, though the lens has some (a phone's often does)."""
    calibration: Path | None = None
    """The filming camera's calibration file instead of `intrinsics`: OpenCV's YAML, XML
    or JSON (as `twinrl twin calibrate` writes) or a COLMAP cameras.txt; scaled to the
    frames' size. With neither, an EXIF 35 mm focal length is used as a first guess."""
    look: bool = True
    """Dress the twin in pictures projected from the frames (the table's top, the
    objects, the room as a backdrop) and judge them on held-out frames (--no-look: flat
    colours, a few seconds sooner)."""
    matching: str = "sequential"
    """How frames are paired for feature matching: sequential (each with the next ten:
    a walk) or exhaustive (every pair: photos taken in no order, or a walk that comes
    back to where it started; slower, growing with the square of the frames)."""
    frames: int = 150
    """Frames to keep for structure from motion (at least 12)."""
    name: str | None = None
    """Scene name (default: from the task)."""
    keep_work: bool = False
    """Keep the frames and the COLMAP database under OUT/work."""
    seed: int = 0
    """Seeds structure from motion, RANSAC and the decomposition."""


BOARDS = ("checkerboard", "charuco")


@dataclass(frozen=True)
class Board:
    """The printed board ``twinrl twin calibrate`` looks for."""

    board: str = "checkerboard"
    """checkerboard, or charuco (a chessboard with ArUco markers in its white squares:
    found even when partly out of view)."""
    squares: tuple[int, int] = (9, 6)
    """Checkerboard: inner corners across x down (a board of 10 x 7 squares has 9x6);
    ChArUco: squares across x down."""
    square_size: float = 0.025
    """Edge of one square (m), as printed (measure it)."""
    marker_size: float = 0.018
    """ChArUco: edge of one ArUco marker (m)."""
    dictionary: str = "DICT_5X5_100"
    """ChArUco: the markers' OpenCV ArUco dictionary."""
