"""ur_rtde's control script as it arrives on the script port: its register offset, and
the path ur_rtde writes into it.

For a path (``moveL``/``moveJ`` with a list of waypoints, ``movePath``) ur_rtde stops the
running script, uploads it again with the path's moves written into the script's
``exec_move_path()`` (after the line ``# inject move path``), each announced by
``signal_async_progress(i)``, and sends command 45, which runs them. The emulator has no
URScript interpreter: it reads those move lines back into :class:`Waypoint` values.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

SCRIPT_END = "# NODE_CONTROL_LOOP_ENDS\nend\n"
PATH_MARK = "# inject move path\n"
_OFFSET = re.compile(r"reg_offset_int = # int register offset\n(\d+)")
_NUMBER = r"\s*([-+0-9.eE]+)\s*"
_MOVE = re.compile(
    rf"(movej|movel|movep)\((p?)\[([^\]]*)\],\s*a={_NUMBER},\s*v={_NUMBER},\s*r={_NUMBER}\)"
)


@dataclass(frozen=True)
class Waypoint:
    """One move of a path: ``movej`` (joint space) or ``movel``/``movep`` (tool space) to
    ``target``, a TCP pose (m, axis-angle rad) when ``pose`` or else joint positions
    (rad), at ``speed`` and ``acceleration`` (rad/s, rad/s^2 for movej; m/s, m/s^2
    otherwise), blending into the next within ``blend`` m."""

    kind: str
    target: np.ndarray
    pose: bool
    speed: float
    acceleration: float
    blend: float


@dataclass(frozen=True)
class ControlScript:
    """A complete control script: its register offset and the path written into it."""

    offset: int
    path: tuple[Waypoint, ...]


def complete_script(text: str) -> ControlScript | None:
    """The control script ``text`` is, or ``None`` while the upload is still incomplete
    (or is not ur_rtde's control script)."""
    if not text.startswith("def rtde_control():") or not text.endswith(SCRIPT_END):
        return None
    found = _OFFSET.search(text)
    return ControlScript(int(found.group(1)) if found else 0, injected_path(text))


def injected_path(text: str) -> tuple[Waypoint, ...]:
    """The moves ur_rtde wrote after :data:`PATH_MARK`, up to the function's ``end``."""
    at = text.find(PATH_MARK)
    if at < 0:
        return ()
    waypoints = []
    for line in text[at + len(PATH_MARK) :].splitlines():
        if line.strip() == "end":
            break
        move = _MOVE.search(line)
        if move:
            kind, pose, values, a, v, r = move.groups()
            target = np.array([float(x) for x in values.split(",")])
            waypoints.append(Waypoint(kind, target, pose == "p", float(v), float(a), float(r)))
    return tuple(waypoints)
