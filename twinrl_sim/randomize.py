"""Visual domain randomisation of a scene spec, recorded so that episodes say how they looked.

``randomize_scene(scene, rng, kinds)`` is a pure function of its inputs: the same seed
gives the same scene. Kinds and their distributions:

- ``lighting``: each light's diffuse intensity ~ U(0.45, 1.0), position jitter ~ U(+-0.3) m;
- ``colors``: table colour ~ U(0.3, 0.8) per channel; each object's colour ~ U(0.1, 0.95);
- ``textures``: table texture ~ uniform over plain / checker / gradient;
- ``camera``: the ``front`` camera's mounting error ~ N(0, 1 cm) and N(0, 0.02 rad) per axis.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SceneSpec

KINDS = ("lighting", "colors", "textures", "camera")


def check_kinds(kinds: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise TwinError(f"unknown randomisation {unknown[0]!r}; choose from {', '.join(KINDS)}")
    return tuple(kinds)


def randomize_scene(
    scene: SceneSpec, rng: np.random.Generator, kinds: tuple[str, ...]
) -> tuple[SceneSpec, dict[str, Any]]:
    """A visually randomised copy of ``scene`` and the record of what was drawn."""
    record: dict[str, Any] = {}
    update: dict[str, Any] = {}
    table = scene.table
    for kind in check_kinds(kinds):
        if kind == "lighting":
            lights = []
            for light in scene.lights:
                scale = float(rng.uniform(0.45, 1.0))
                shift = rng.uniform(-0.3, 0.3, 3) * [1, 1, 0.3]
                lights.append(
                    light.model_copy(
                        update={
                            "diffuse": (scale, scale, scale),
                            "pos": tuple(float(p) for p in np.asarray(light.pos) + shift),
                        }
                    )
                )
            update["lights"] = lights
            record["lighting"] = [{"diffuse": x.diffuse[0], "pos": list(x.pos)} for x in lights]
        elif kind == "colors":
            rgb = tuple(float(c) for c in rng.uniform(0.3, 0.8, 3))
            table = table.model_copy(update={"rgba": (*rgb, 1.0)})
            objects = [
                o.model_copy(update={"rgba": (*(float(c) for c in rng.uniform(0.1, 0.95, 3)), 1.0)})
                for o in scene.objects
            ]
            update["objects"] = objects
            record["colors"] = {"table": list(rgb), **{o.name: list(o.rgba[:3]) for o in objects}}
        elif kind == "textures":
            texture = str(rng.choice(["plain", "checker", "gradient"]))
            table = table.model_copy(update={"texture": texture})
            record["textures"] = {"table": texture}
        elif kind == "camera":
            xyz = [float(v) for v in rng.normal(0.0, 0.01, 3)]
            rpy = [float(v) for v in rng.normal(0.0, 0.02, 3)]
            effects = {**scene.effects, "camera_pose": {"camera": "front", "xyz": xyz, "rpy": rpy}}
            update["effects"] = effects
            record["camera"] = {"camera": "front", "xyz": xyz, "rpy": rpy}
    update["table"] = table
    return scene.model_copy(update=update), record
