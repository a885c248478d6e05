"""Walks of a compiled model's body tree: the bodies below one, and those above one."""

from __future__ import annotations

import mujoco


def subtree(model: mujoco.MjModel, root: int) -> set[int]:
    """Ids of body ``root`` and every body below it."""
    bodies = {root}
    for body in range(model.nbody):
        parent = body
        while parent > 0 and parent not in bodies:
            parent = int(model.body_parentid[parent])
        if parent in bodies:
            bodies.add(body)
    return bodies


def ancestors(model: mujoco.MjModel, body: int) -> set[int]:
    """Ids of ``body`` and every body on its chain up to the world (the world left out)."""
    chain = set()
    while body > 0:
        chain.add(body)
        body = int(model.body_parentid[body])
    return chain
