"""What a real phone does to the light a rendered frame is made of: lens distortion,
auto exposure that hunts, sensor noise and lossy compression. Rendering alone gives
pinhole, evenly lit, noiseless frames that structure from motion finds easier than any
real clip, so the twin build's realistic test set passes its renders through these.

The ground truth for a distorted clip is the pinhole camera it was rendered with plus
OpenCV's radial-tangential model (``k1 k2 p1 p2``): :func:`pinhole_intrinsics` and
:attr:`CameraTraits.distortion`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class CameraTraits:
    """A real camera's traits, applied to rendered frames. Defaults: an ideal camera."""

    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """OpenCV's k1 k2 p1 p2 of the lens (a phone's main camera: k1 about 0.1)."""
    noise: float = 0.0
    """Standard deviation of the sensor noise, in grey levels of 255."""
    exposure_drift: float = 0.0
    """Amplitude of the auto exposure's gain swings (0.15: +-15 %)."""
    jpeg_quality: int | None = None
    """Frames saved as JPEG of this quality (a phone's stills: about 85); None: lossless."""

    @property
    def distorted(self) -> bool:
        return any(self.distortion)


REALISTIC_TRAITS = CameraTraits(
    distortion=(0.12, -0.25, 0.001, -0.0015), noise=4.0, exposure_drift=0.15, jpeg_quality=80
)


def pinhole_intrinsics(width: int, height: int, fovy_deg: float) -> tuple[float, ...]:
    """fx fy cx cy (pixels) of a pinhole camera with vertical field of view ``fovy_deg``,
    as MuJoCo renders: square pixels, the principal point at the image's centre."""
    f = (height / 2) / math.tan(math.radians(fovy_deg) / 2)
    return (f, f, width / 2, height / 2)


def camera_matrix(intrinsics: tuple[float, ...]) -> np.ndarray:
    fx, fy, cx, cy = intrinsics[:4]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def distortion_maps(
    intrinsics: tuple[float, ...], distortion: tuple[float, ...], size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps that turn a pinhole image of ``size`` (width, height) into what
    the lens with ``distortion`` shows: each distorted pixel samples the pinhole image
    where its undistorted ray lands."""
    width, height = size
    grid = np.stack(np.meshgrid(np.arange(width), np.arange(height)), axis=-1)
    pixels = grid.reshape(-1, 1, 2).astype(np.float64)
    matrix = camera_matrix(intrinsics)
    ideal = cv2.undistortPoints(pixels, matrix, np.asarray(distortion, float), P=matrix)
    ideal = ideal.reshape(height, width, 2).astype(np.float32)
    return ideal[..., 0], ideal[..., 1]


class TraitApplier:
    """Applies ``traits`` to the frames of one clip, in order (the exposure drifts
    smoothly from frame to frame; the noise is drawn from ``rng``)."""

    def __init__(
        self,
        traits: CameraTraits,
        intrinsics: tuple[float, ...],
        size: tuple[int, int],
        frames: int,
        rng: np.random.Generator,
    ) -> None:
        self.traits, self.rng = traits, rng
        self.maps = None
        if traits.distorted:
            self.maps = distortion_maps(intrinsics, traits.distortion, size)
        phase = rng.uniform(0, 2 * math.pi, 2)
        t = np.linspace(0.0, 1.0, max(frames, 1))
        swing = 0.6 * np.sin(2 * math.pi * 1.3 * t + phase[0]) + 0.4 * np.sin(
            2 * math.pi * 3.1 * t + phase[1]
        )
        self.gains = 1.0 + traits.exposure_drift * swing

    def __call__(self, image: np.ndarray, index: int) -> np.ndarray:
        """Frame ``index`` (RGB uint8) as the camera would have delivered it."""
        frame = image.astype(np.float32)
        if self.maps is not None:
            frame = cv2.remap(frame, *self.maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        frame *= self.gains[min(index, len(self.gains) - 1)]
        if self.traits.noise:
            frame += self.rng.normal(0.0, self.traits.noise, frame.shape).astype(np.float32)
        return np.clip(frame.round(), 0, 255).astype(np.uint8)
