"""The sensor noise of each measured signal family: the unit of every gap residual.

A joint angle (rad), a torque (N m) and a position (m) weigh alike once divided by
their noise, and a twin that explains everything but that noise has residuals of 1.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from twinrl_data.errors import SettingError


@dataclass(frozen=True)
class NoiseFloor:
    """Standard deviation of each measured signal family: the residuals' unit.

    The defaults are those of a UR e-series arm's joint encoders, velocity estimate,
    TCP pose and joint torque estimate, of a tracked object's position, and of a
    camera image compared in standardised grey levels and in colour.
    """

    q: float = 2e-4  # rad
    qd: float = 2e-3  # rad/s
    tcp: float = 3e-4  # m
    tau: float = 0.05  # N m
    object: float = 1e-3  # m
    image: float = 0.05  # standardised grey level of a compared image (see gap.camera)
    colour: float = 0.02  # colour level (0-1) of a box-averaged image (see gap.appearance)

    @classmethod
    def parse(cls, text: str) -> NoiseFloor:
        """``q=2e-4,tau=0.1`` -> a NoiseFloor with those entries changed."""
        known = {f.name for f in fields(cls)}
        values = {}
        for item in filter(None, (p.strip() for p in text.split(","))):
            key, _, value = item.partition("=")
            if key not in known:
                raise SettingError(
                    "noise",
                    f"names an unknown signal family '{key}'; use {', '.join(sorted(known))}",
                )
            try:
                values[key] = float(value)
            except ValueError:
                raise SettingError("noise", f"'{item}' needs a number, e.g. {key}=1e-3") from None
            if not values[key] > 0:
                raise SettingError("noise", f"{key} must be positive, got {value}")
        return cls(**values)
