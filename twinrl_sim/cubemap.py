"""Cube maps in OpenGL's layout, as MuJoCo stores them: six square faces stacked
(+x, -x, +y, -y, +z, -z), each texel the colour seen looking along its direction."""

from __future__ import annotations

import numpy as np

# Per face: the direction of texel (s, t) in [-1, 1]^2 (s along the columns, t down the
# rows), as the axis it faces plus s and t along the other two.
_FACES = (
    lambda s, t: (np.ones_like(s), -t, -s),
    lambda s, t: (-np.ones_like(s), -t, s),
    lambda s, t: (s, np.ones_like(s), t),
    lambda s, t: (s, -np.ones_like(s), -t),
    lambda s, t: (s, -t, np.ones_like(s)),
    lambda s, t: (-s, -t, -np.ones_like(s)),
)


def cube_directions(size: int) -> np.ndarray:
    """(6, size, size, 3) unit directions of a cube map's texel centres."""
    centres = (np.arange(size) + 0.5) / size * 2 - 1
    t, s = np.meshgrid(centres, centres, indexing="ij")
    faces = np.stack([np.stack(face(s, t), axis=-1) for face in _FACES])
    return faces / np.linalg.norm(faces, axis=-1, keepdims=True)


def cube_lookup(cube: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The texels of ``cube`` (6*size, size, C) that ``directions`` (..., 3) look at."""
    size = cube.shape[1]
    d = directions.reshape(-1, 3)
    axis = np.abs(d).argmax(axis=1)
    major = d[np.arange(len(d)), axis]
    face = 2 * axis + (major < 0)
    x, y, z = (d / np.abs(major)[:, None]).T
    s = np.select([face == 0, face == 1, face == 5], [-z, z, -x], default=x)
    t = np.select([face == 2, face == 3], [z, -z], default=-y)
    col = np.clip(((s + 1) / 2 * size).astype(int), 0, size - 1)
    row = np.clip(((t + 1) / 2 * size).astype(int), 0, size - 1)
    return cube[face * size + row, col].reshape(*directions.shape[:-1], cube.shape[-1])
