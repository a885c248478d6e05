"""Planar geometry on the table: distances, headings and wrapped angles."""

from __future__ import annotations

import math

import numpy as np


def planar_distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a)[:2] - np.asarray(b)[:2]))


def yaw_of(quat: np.ndarray) -> float:
    """Heading (rad) of a body's x axis projected on the table."""
    w, x, y, z = quat
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def wrap_angle(angle: float, period: float = 2 * math.pi) -> float:
    """``angle`` wrapped to [-period/2, period/2)."""
    return (angle + period / 2) % period - period / 2
