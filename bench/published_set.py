"""A published photo set a benchmark reads: every file checked against the set's
SHA-256 manifest in ``bench/data`` before anything runs, so a figure always comes from
the very files it names; then mapped, and its markers located."""

from __future__ import annotations

import hashlib
import shutil
import sys
import tempfile
import time
from pathlib import Path

from twinrl_sim.reconstruct.align import TagSighting, locate_tags
from twinrl_sim.reconstruct.sfm import SparseModel, run_sfm


def checked_files(folder: Path, manifest: Path, where: str) -> list[Path]:
    """The manifest's files under ``folder`` (in the manifest's order), each matching
    its digest; exits with one line naming what is missing or different. ``where`` says
    which folder of which clone to give."""
    expected = dict(line.split()[::-1] for line in manifest.read_text().splitlines())
    missing = [name for name in expected if not (folder / name).is_file()]
    if missing:
        sys.exit(
            f"{folder}: {len(missing)} of the set's {len(expected)} files are missing "
            f"(e.g. {missing[0]}); give {where}"
        )
    for name, digest in expected.items():
        if hashlib.sha256((folder / name).read_bytes()).hexdigest() != digest:
            sys.exit(f"{folder / name} differs from the published file (SHA-256); re-clone")
    return [folder / name for name in expected]


def map_and_locate(
    photos: list[Path],
    family: str,
    intrinsics: tuple[float, ...],
    *,
    seed: int = 0,
    refine_distortion: bool = False,
) -> tuple[SparseModel, dict[int, TagSighting], float, float]:
    """The photos mapped with the set's intrinsics, every pair matched (sets go around
    and back), and the markers of ``family`` triangulated: the model, the markers, the
    seconds mapping took and the seconds in all."""
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "frames"
        frames.mkdir()
        for photo in photos:
            shutil.copy(photo, frames / photo.name)
        start = time.perf_counter()
        model = run_sfm(
            frames,
            Path(tmp) / "sfm",
            seed=seed,
            intrinsics=intrinsics,
            refine_distortion=refine_distortion,
            matching="exhaustive",
        )
        mapped = time.perf_counter() - start
        tags = locate_tags(model, frames, family)
    return model, tags, mapped, time.perf_counter() - start
