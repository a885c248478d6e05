"""The grasp in the Rerun view, from what an episode logs and nothing else.

An episode logs the gripper's opening (``gripper.opening``, m, in the state), its command
(the action's last entry, closed at or above :data:`GRIPPER_CLOSED`), the objects' poses
where the world knows them (twin, plant, an emulated cell) and, where a cell measures
it, the force at the TCP (``observation.wrench``, base frame). No world logs contacts;
the view draws the twin's (:mod:`twinrl_data.contact_view`). From these:

- **in hand**: an object is held at a step when the fingers, commanded closed since the
  step before, have stopped (:data:`STILL`) short of both closed (:data:`EMPTY`: they
  closed on nothing) and open, and it is the object nearest the TCP, within
  :data:`REACH` of it. In 3D the held object carries a gold ``in hand`` marker; the plot
  ``signals/grasp`` has the opening (cm), the command (darker) and, for each object
  ever held, 1 while it is.
- **the TCP's force**: an arrow from the TCP (:data:`ARROW_M_PER_N`), labelled with its
  size, and the force's components plotted under ``signals/force``.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from twinrl_data import schema as contract
from twinrl_data.mcap_log import pose_groups
from twinrl_data.schema import GRIPPER_CLOSED, GRIPPER_OPENING
from twinrl_data.timeline import step_times

STILL = 0.001  # m the opening may change in a step with the fingers stopped
EMPTY = 0.002  # m; at or below it the fingers closed on nothing
REACH = 0.04  # m from the TCP within which the nearest object is between the fingers
ARROW_M_PER_N = 0.005  # the force arrow's length per newton
HELD_COLOR = [255, 200, 0]
FORCE_COLOR = [230, 60, 60]
AXIS_COLORS = ([220, 60, 60], [60, 180, 60], [60, 90, 220])  # x, y, z


def _state(episode: contract.Episode) -> tuple[list[str], np.ndarray]:
    return episode.meta.names.get(contract.STATE, []), episode.data[contract.STATE]


def held_objects(episode: contract.Episode) -> dict[str, np.ndarray]:
    """Each object whose pose ``episode`` logs: whether it is in hand at each step (see
    the module docstring); empty where the episode logs no opening, TCP or objects."""
    names, state = _state(episode)
    tcp = pose_groups(names).get("tcp")
    environment = episode.data.get(contract.ENVIRONMENT_STATE)
    frames = pose_groups(episode.meta.names.get(contract.ENVIRONMENT_STATE, []))
    if tcp is None or GRIPPER_OPENING not in names or environment is None or not frames:
        return {}
    positions = np.stack([environment[:, idx[:3]] for idx in frames.values()])
    held = held_at(
        state[:, names.index(GRIPPER_OPENING)],
        episode.data[contract.ACTION][:, -1] >= GRIPPER_CLOSED,
        state[:, tcp[:3]],
        positions,
    )
    return dict(zip(frames, held, strict=True))


def held_at(
    opening: np.ndarray,
    commanded: np.ndarray,
    tcp: np.ndarray,
    positions: np.ndarray,
    widest: float | None = None,
) -> np.ndarray:
    """Whether each object is in hand at each step, (n_objects, T): ``opening`` (T,) m,
    ``commanded`` (T,) the close commanded, ``tcp`` (T, 3), the objects' ``positions``
    (n_objects, T, 3); ``widest`` the widest opening seen (default: ``opening``'s)."""
    widest = float(opening.max()) if widest is None else widest
    gripping = np.zeros(len(opening), bool)
    gripping[1:] = (
        commanded[:-1]
        & (np.abs(np.diff(opening)) < STILL)
        & (opening[1:] > EMPTY)
        & (opening[1:] < widest - EMPTY)
    )
    distance = np.linalg.norm(positions - tcp[None], axis=2)
    near = gripping & (distance.min(axis=0) < REACH)
    nearest = distance.argmin(axis=0)
    return np.stack([near & (nearest == i) for i in range(len(positions))])


class LiveGrasp:
    """The object in hand step by step, as a recording goes (:func:`held_at` on the
    last two steps, the widest opening so far)."""

    def __init__(self) -> None:
        self._last: tuple[float, bool] | None = None
        self._widest = 0.0

    def update(
        self, opening: float, commanded: bool, tcp: np.ndarray, objects: dict[str, np.ndarray]
    ) -> str | None:
        """The object in hand now (None: none), given this step's opening (m), whether
        the close is commanded, the TCP and each object's position."""
        self._widest = max(self._widest, opening)
        last, self._last = self._last, (opening, commanded)
        if last is None or not objects:
            return None
        positions = np.stack([[p, p] for p in objects.values()])
        held = held_at(
            np.array([last[0], opening]), np.array([last[1], commanded]),
            np.stack([tcp, tcp]), positions, self._widest,
        )[:, 1]  # fmt: skip
        return next((name for name, h in zip(objects, held, strict=True) if h), None)


def has_grasp(episode: contract.Episode) -> bool:
    """Whether ``episode`` logs the gripper's opening (so the grasp plot has a line)."""
    return GRIPPER_OPENING in _state(episode)[0]


def log_grasp(
    episode: contract.Episode, label: str, color: list[int], recording: rr.RecordingStream
) -> None:
    """Log ``episode``'s grasp and TCP force (see the module docstring) under ``label``,
    one column per signal on the timelines ``step`` and ``time``."""
    times = step_times(len(episode), episode.meta.fps)
    names, state = _state(episode)
    if GRIPPER_OPENING in names:
        opening = state[:, names.index(GRIPPER_OPENING)].astype(float) * 100
        command = episode.data[contract.ACTION][:, -1].astype(float)
        _plot(f"signals/grasp/opening/{label}", f"opening (cm) {label}", opening, color,
              times, recording)  # fmt: skip
        _plot(f"signals/grasp/command/{label}", f"command {label}", command,
              [c // 2 for c in color], times, recording)  # fmt: skip
    for frame, held in held_objects(episode).items():
        if not held.any():  # never in hand: no line, no marker
            continue
        _plot(f"signals/grasp/{frame}/{label}", f"{frame} in hand {label}", held * 1.0,
              HELD_COLOR, times, recording)  # fmt: skip
        count = int(held.sum())
        marker = rr.Points3D.columns(
            positions=np.zeros((count, 3)), radii=[0.02] * count,
            colors=[HELD_COLOR] * count, labels=["in hand"] * count,
        ).partition(held.astype(int))  # fmt: skip
        rr.send_columns(f"world/{label}/objects/{frame}/in_hand", indexes=times,
                        columns=marker, recording=recording)  # fmt: skip
    wrench = episode.data.get(contract.WRENCH)
    if wrench is None:
        return
    force = wrench[:, :3].astype(float)
    for axis, values, line in zip("xyz", force.T, AXIS_COLORS, strict=True):
        _plot(f"signals/force/{axis}/{label}", f"force {axis} (N) {label}", values, line,
              times, recording)  # fmt: skip
    tcp = pose_groups(names).get("tcp")
    if tcp is not None:
        arrows = rr.Arrows3D.columns(
            origins=state[:, tcp[:3]], vectors=force * ARROW_M_PER_N,
            colors=[FORCE_COLOR] * len(force),
            labels=[f"{f:.0f} N" for f in np.linalg.norm(force, axis=1)],
        )  # fmt: skip
        rr.send_columns(f"world/{label}/tcp_force", indexes=times, columns=arrows,
                        recording=recording)  # fmt: skip


def _plot(
    path: str,
    name: str,
    values: np.ndarray,
    color: list[int],
    times: list[rr.TimeColumn],
    recording: rr.RecordingStream,
) -> None:
    rr.log(path, rr.SeriesLines(colors=[color], names=name), static=True, recording=recording)
    rr.send_columns(path, indexes=times, columns=rr.Scalars.columns(scalars=values),
                    recording=recording)  # fmt: skip
