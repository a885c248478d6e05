"""Frames for structure from motion: from a video file (PyAV) or a folder of images,
keep sharp ones spread over the clip, and refuse clips that cannot work.

Sharpness is the variance of the Laplacian of the grey image. The clip is cut into as
many equal spans as frames are wanted and the sharpest frame of each span is kept, so
the kept frames follow the camera's path (parallax) instead of bunching where it
lingered. A clip is refused when it is too blurry overall or when the camera barely
moves (optical flow between the kept frames), with what to film differently.

The clip is streamed twice (sharpness first, then the chosen frames), so memory does not
grow with its length: a minute of 4K video is never held whole.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

from twinrl_sim.errors import TwinError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")
MIN_SHARPNESS = 15.0  # variance of the Laplacian below which a frame is a blur
# Median image motion over the clip, in image widths, below which the camera stayed put.
# Hand-held walks of 12 to 50 deg over a table measure 0.22-0.28 (hand shake moves the
# view as much as the sweep does) and structure from motion maps every frame of each;
# a camera on a stand measures 0. Above this, mapping judges the walk.
MIN_TRAVEL = 0.1
MIN_FRAMES = 12
FLOW_WIDTH = 640  # px: kept frames are shrunk to this width to measure camera travel


class CaptureError(TwinError):
    """A clip or photo set that reconstruction cannot use; says what to capture instead."""


@dataclass
class FrameSelection:
    """The frames kept for SfM (written as images) and why."""

    paths: list[Path]
    source_indices: list[int]  # index of each kept frame in the clip
    sharpness: list[float]
    frames_in_clip: int
    travel: float  # median image motion across the kept frames, in image widths
    dropped_blurry: int = 0


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (higher: sharper)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def stream_frames(source: Path) -> Iterator[np.ndarray]:
    """The RGB frames of a video file or an image folder, one at a time."""
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CaptureError(f"{source} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        for path in files:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise CaptureError(f"{path} is not a readable image")
            yield cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        return
    if not source.is_file():
        raise CaptureError(f"{source} does not exist; give a video file or a folder of images")
    try:
        with av.open(str(source)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"  # decode on every core
            for frame in container.decode(stream):
                yield frame.to_ndarray(format="rgb24")
    except (av.error.FFmpegError, IndexError) as err:
        raise CaptureError(f"{source} is not a readable video ({err})") from None


def _flow_grey(frame: np.ndarray) -> np.ndarray:
    """The grey frame at most :data:`FLOW_WIDTH` wide, for measuring camera travel."""
    grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
    if grey.shape[1] <= FLOW_WIDTH:
        return grey
    height = round(grey.shape[0] * FLOW_WIDTH / grey.shape[1])
    return cv2.resize(grey, (FLOW_WIDTH, height), interpolation=cv2.INTER_AREA)


def _travel(greys: list[np.ndarray]) -> float:
    """Summed median optical-flow motion between consecutive frames, in image widths."""
    total = 0.0
    width = greys[0].shape[1]
    previous = greys[0]
    for grey in greys[1:]:
        points = cv2.goodFeaturesToTrack(previous, 200, 0.01, 8)
        if points is not None:
            moved, status, _ = cv2.calcOpticalFlowPyrLK(previous, grey, points, None)
            ok = status.ravel() == 1
            if ok.any():
                total += float(np.median(np.linalg.norm((moved - points)[ok], axis=-1)))
        previous = grey
    return total / width


def select_frames(
    source: str | Path,
    out_dir: str | Path,
    *,
    target: int = 150,
    progress: Callable[[int, int], None] | None = None,
) -> FrameSelection:
    """Pick up to ``target`` sharp frames spread over ``source`` and write them as PNGs
    into ``out_dir``; raise :class:`CaptureError` when the clip cannot work."""
    source, out_dir = Path(source), Path(out_dir)
    scores = np.array([sharpness(frame) for frame in stream_frames(source)])
    sharp = scores >= MIN_SHARPNESS
    if sharp.sum() < MIN_FRAMES:
        raise CaptureError(
            f"{source}: only {int(sharp.sum())} of {len(scores)} frames are sharp "
            f"(Laplacian variance >= {MIN_SHARPNESS:g}); film slower, in better light, "
            "and let the phone focus on the table"
        )
    spans = np.array_split(np.arange(len(scores)), min(target, len(scores)))
    kept = []
    for span in spans:
        candidates = span[sharp[span]]
        if len(candidates):
            kept.append(int(candidates[np.argmax(scores[candidates])]))
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    paths, greys, wanted = [], [], set(kept)
    for index, frame in enumerate(stream_frames(source)):
        if index not in wanted:
            continue
        path = out_dir / f"frame_{index:05d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        paths.append(path)
        greys.append(_flow_grey(frame))
        if progress is not None:
            progress(len(paths), len(kept))
    travel = _travel(greys)
    if travel < MIN_TRAVEL:
        for path in paths:
            path.unlink()
        if created:
            shutil.rmtree(out_dir, ignore_errors=True)
        raise CaptureError(
            f"{source}: the camera barely moves (the view shifts {travel:.2f} image widths "
            f"in all, at least {MIN_TRAVEL:g} needed); walk around the table, keeping it "
            "in view, instead of filming from one spot"
        )
    return FrameSelection(
        paths=paths,
        source_indices=kept,
        sharpness=[float(scores[i]) for i in kept],
        frames_in_clip=len(scores),
        travel=travel,
        dropped_blurry=int((~sharp).sum()),
    )
