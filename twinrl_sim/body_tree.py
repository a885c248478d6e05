"""Walks of a compiled model's body tree: the bodies below one, and those above one."""

from __future__ import annotations

import mujoco


def subtree(model: mujoco.MjModel, root: int) -> set[int]:
    """Ids of body ``root`` and every body below it (a compiled model numbers every body
    after its parent, so one pass from the root finds them all)."""
    bodies = {root}
    for body in range(root + 1, model.nbody):
        if int(model.body_parentid[body]) in bodies:
            bodies.add(body)
    return bodies


def ancestors(model: mujoco.MjModel, body: int) -> set[int]:
    """Ids of ``body`` and every body on its chain up to the world (the world left out)."""
    chain = set()
    while body > 0:
        chain.add(body)
        body = int(model.body_parentid[body])
    return chain
