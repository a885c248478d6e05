"""The plant: the stand-in for the real cell.

A second MuJoCo world built from the twin's scene spec plus hidden effects (physical
ones and its ``appearance``), read through noisy sensors
(:class:`~twinrl_robot.wrappers.SensorNoise`). It is opened like any robot, with
:func:`twinrl_robot.backends.open_robot` (``"plant"``). It is never used as the twin and
nothing reads its hidden effects except to generate data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from twinrl_sim.effects import load_effects, validate_effects

DEFAULT_EFFECTS_FILE = Path(__file__).resolve().parent / "plants" / "default.yaml"


def hidden_effects(effects: dict[str, dict[str, Any]] | str | Path | None) -> dict[str, Any]:
    """The plant's hidden effects: ``None`` the built-in plant (``plants/default.yaml``),
    a path an effects YAML, a mapping itself (validated); ``{}`` means none."""
    if effects is None:
        return load_effects(DEFAULT_EFFECTS_FILE)
    if isinstance(effects, str | Path):
        return load_effects(effects)
    return validate_effects(effects)
