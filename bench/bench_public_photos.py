"""Structure from motion and tags on real public photos: the AprilTag project's
``images/mapping_feb_2014`` set (72 iPhone photos, 816x612, of a room's walls with 20
tag36h11 tags printed alike, 12.7 cm; the camera's intrinsics in the set's
``calibration/calib.txt``). With one tag's size given (the tag seen most), every other
tag's edges must come out at 12.7 cm: median error <= 1 %, worst <= 3 %. The photos
were taken around the room and back, so they are matched exhaustively. The calibration
gives no lens distortion, which an iPhone has: it is refined while mapping
(``refine_distortion``, as ``twin build --refine-distortion`` does).

The photos are not in this repository. Get them with::

    git clone https://github.com/swatbotics/apriltag
    python bench/bench_public_photos.py apriltag/images/mapping_feb_2014

The benchmark checks each photo against ``bench/data/apriltag_mapping_feb_2014.sha256``
before it starts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from published_set import checked_files, map_and_locate

MANIFEST = Path(__file__).parent / "data" / "apriltag_mapping_feb_2014.sha256"
INTRINSICS = (765.00, 764.18, 393.72, 304.66)  # calibration/calib.txt of the set
TAG_EDGE = 0.127  # m, every tag of the set
TARGET_MEDIAN, TARGET_WORST = 0.01, 0.03


def main(
    folder: Annotated[Path, typer.Argument(help="The set's folder, images/mapping_feb_2014.")],
    seed: Annotated[int, typer.Option(help="Seeds structure from motion.")] = 0,
    refine_distortion: Annotated[
        bool,
        typer.Option(
            help="Estimate the iPhone's lens distortion, which the set's calibration leaves "
            "out (the focal length and principal point held)."
        ),
    ] = True,
) -> None:
    photos = sorted(
        checked_files(
            folder,
            MANIFEST,
            "the images/mapping_feb_2014 folder of a clone of https://github.com/swatbotics/apriltag",
        )
    )
    model, tags, mapped, seconds = map_and_locate(
        photos, "tag36h11", INTRINSICS, seed=seed, refine_distortion=refine_distortion
    )
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
