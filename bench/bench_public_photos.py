"""Structure from motion and tags on real public photos: the AprilTag project's
``images/mapping_feb_2014`` set (72 iPhone photos, 816x612, of a room's walls with 20
tag36h11 tags printed alike, 12.7 cm; the camera's intrinsics in the set's
``calibration/calib.txt``). With one tag's size given (the tag seen most), every other
tag's edges must come out at 12.7 cm: median error <= 1 %, worst <= 3 %. The photos
were taken around the room and back, so they are matched exhaustively.

The photos are not in this repository. Get them with::

    git clone https://github.com/swatbotics/apriltag
    python bench/bench_public_photos.py apriltag/images/mapping_feb_2014

The benchmark checks each photo against ``bench/data/apriltag_mapping_feb_2014.sha256``
before it starts.
"""

from __future__ import annotations

import hashlib
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from twinrl_sim.reconstruct.align import locate_tags
from twinrl_sim.reconstruct.sfm import run_sfm

MANIFEST = Path(__file__).parent / "data" / "apriltag_mapping_feb_2014.sha256"
INTRINSICS = (765.00, 764.18, 393.72, 304.66)  # calibration/calib.txt of the set
TAG_EDGE = 0.127  # m, every tag of the set
TARGET_MEDIAN, TARGET_WORST = 0.01, 0.03


def _checked_photos(folder: Path) -> list[Path]:
    """The set's photos in ``folder``, each matching the manifest; exits with one line
    naming what is missing or different."""
    expected = dict(line.split()[::-1] for line in MANIFEST.read_text().splitlines())
    missing = [name for name in expected if not (folder / name).is_file()]
    if missing:
        sys.exit(
            f"{folder}: {len(missing)} of the set's {len(expected)} photos are missing "
            f"(e.g. {missing[0]}); give the images/mapping_feb_2014 folder of a clone of "
            "https://github.com/swatbotics/apriltag"
        )
    for name, digest in expected.items():
        if hashlib.sha256((folder / name).read_bytes()).hexdigest() != digest:
            sys.exit(f"{folder / name} differs from the published photo (SHA-256); re-clone")
    return [folder / name for name in sorted(expected)]


def main(
    folder: Annotated[Path, typer.Argument(help="The set's folder, images/mapping_feb_2014.")],
    seed: Annotated[int, typer.Option(help="Seeds structure from motion.")] = 0,
) -> None:
    photos = _checked_photos(folder)
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "frames"
        frames.mkdir()
        for photo in photos:
            shutil.copy(photo, frames / photo.name)
        start = time.perf_counter()
        model = run_sfm(
            frames, Path(tmp) / "sfm", seed=seed, intrinsics=INTRINSICS, matching="exhaustive"
        )
        mapped = time.perf_counter() - start
        tags = locate_tags(model, frames, "tag36h11")
        seconds = time.perf_counter() - start
    edges = {
        tag_id: float(
            np.mean(np.linalg.norm(np.roll(s.corners_sfm, -1, 0) - s.corners_sfm, axis=1))
        )
        for tag_id, s in tags.items()
    }
    reference = max(tags, key=lambda tag_id: (len(tags[tag_id].frames), -tag_id))
    scale = TAG_EDGE / edges[reference]
    errors = {
        tag_id: scale * edge / TAG_EDGE - 1 for tag_id, edge in edges.items() if tag_id != reference
    }
    print("| tag | photos | edge (mm) | error (%) |")
    print("|---|---|---|---|")
    for tag_id in sorted(tags):
        edge = 1000 * scale * edges[tag_id]
        error = "reference" if tag_id == reference else f"{100 * errors[tag_id]:+.2f}"
        print(f"| {tag_id} | {len(tags[tag_id].frames)} | {edge:.1f} | {error} |")
    worst = max(abs(e) for e in errors.values())
    median = float(np.median(np.abs(list(errors.values()))))
    print(
        f"\n{model.registered}/{len(photos)} photos registered in {mapped:.0f} s, {len(tags)} "
        f"tags located ({seconds:.0f} s in all); other tags' edges off by {100 * median:.2f} % "
        f"median (target {100 * TARGET_MEDIAN:.0f} %), {100 * worst:.2f} % worst (target "
        f"{100 * TARGET_WORST:.0f} %)"
    )


if __name__ == "__main__":
    typer.run(main)
