"""Structure from motion and markers on real public photos with measured distances: the
scene-reconstruction test set of Sandia's OpenCSP (54 photos, 1728x1152 grey JPEG, of
ArUco 4x4 markers on a floor and a wall several metres across; the camera's
calibration in the set's ``camera.h5``; 13 distances between markers' origin corners
measured on site, in ``point_pair_distances.csv``).

Each measured distance is reproduced with the model scaled by the other twelve (leave
one out, so no distance is its own reference): error <= 1 % for every pair.

The set is not in this repository. Get it with::

    git clone https://github.com/sandialabs/OpenCSP
    python bench/bench_marker_distances.py \\
        OpenCSP/opencsp/app/scene_reconstruction/test/data/data_measurement

The benchmark checks each file against ``bench/data/opencsp_scene_reconstruction.sha256``
before it starts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from published_set import checked_files, map_and_locate

MANIFEST = Path(__file__).parent / "data" / "opencsp_scene_reconstruction.sha256"
WHERE = (
    "the opencsp/app/scene_reconstruction/test/data/data_measurement folder of a clone of "
    "https://github.com/sandialabs/OpenCSP"
)
# camera.h5 of the set (Camera/intrinsic_mat and distortion_coef, OpenCV's k1, k2, p1,
# p2), read with h5py once: the set's downsampling divided the whole matrix by five, so
# its entries are the 1728x1152 photos' own.
INTRINSICS = (
    937.474756,
    935.571561,
    869.741631,
    576.088437,
    -0.05576391,
    0.03966674,
    -0.00055473,
    0.00049181,
)
ORIGIN_CORNER = 0  # the distances are between markers' corner 0 (OpenCV's top-left)
TARGET = 0.01


def main(
    folder: Annotated[
        Path, typer.Argument(help="The set's data_measurement folder, in a clone of OpenCSP.")
    ],
    seed: Annotated[int, typer.Option(help="Seeds structure from motion.")] = 0,
) -> None:
    files = checked_files(folder, MANIFEST, WHERE)
    photos = [f for f in files if f.suffix == ".JPG"]
    pairs = np.loadtxt(folder / "point_pair_distances.csv", delimiter=",", skiprows=1, ndmin=2)
    model, tags, mapped, seconds = map_and_locate(photos, "aruco4x4", INTRINSICS, seed=seed)
    rows = []
    for a, b, measured in pairs:
        a, b = int(a), int(b)
        if a in tags and b in tags:
            corners = tags[a].corners_sfm[ORIGIN_CORNER], tags[b].corners_sfm[ORIGIN_CORNER]
            rows.append((a, b, measured, float(np.linalg.norm(corners[0] - corners[1]))))
    missing = len(pairs) - len(rows)
    if len(rows) < 2:
        raise SystemExit(f"only {len(rows)} of the {len(pairs)} measured pairs were located")
    scales = np.array([measured / model_length for _, _, measured, model_length in rows])
    print("| markers | measured (m) | reproduced (m) | error (%) |")
    print("|---|---|---|---|")
    errors = []
    for i, (a, b, measured, model_length) in enumerate(rows):
        reproduced = float(np.delete(scales, i).mean()) * model_length
        errors.append(reproduced / measured - 1)
        print(f"| {a}-{b} | {measured:.3f} | {reproduced:.4f} | {100 * errors[-1]:+.2f} |")
    errors = np.abs(errors)
    print(
        f"\n{model.registered}/{len(photos)} photos registered in {mapped:.0f} s, {len(tags)} "
        f"markers located ({seconds:.0f} s in all); {len(rows)} of {len(pairs)} measured "
        f"distances reproduced"
        + (f" ({missing} pairs not located)" if missing else "")
        + f", off by {100 * np.median(errors):.2f} % median, {100 * errors.max():.2f} % worst "
        f"(target {100 * TARGET:.0f} %)"
    )


if __name__ == "__main__":
    typer.run(main)
