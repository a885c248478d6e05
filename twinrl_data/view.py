"""Rerun inspection of episodes: cameras, signals, intervention spans and the cell in 3D.

:func:`log_episodes` writes one or more episodes into a Rerun recording on the timeline
``step`` (and ``time`` in seconds), under a blueprint:

- left: each camera (``cameras/<label>/<camera>``, or its frustum in the cell, below);
- middle: the 3D scene (``world``): TCP path and pose, object poses and, given a
  :class:`CellModel` (the twin supplies one), the cell itself: the arm's links, the
  gripper's fingers, the table and the objects as shapes logged once
  (``world/<label>/cell/<body>/<i>``, static) and moved by one transform per body and
  step (``world/<label>/cell/<body>``), so a long episode stays small; each camera the
  cell mounts is a pinhole frustum at its pose with its images inside
  (``world/<label>/cell/<body>/<camera>``: the wrist camera rides the flange), which
  the camera views show too, so no image is logged twice;
- right: time series of joint positions against joint targets, the grasp (and the
  TCP's force where it is logged), executed against policy-proposed actions, reward and
  success, with intervention spans in red.

The grasp, drawn from what the episode logs, is :mod:`twinrl_data.grasp_view`'s: the
held object marked ``in hand`` in 3D, the force at the TCP as an arrow. With a cell,
what the robot touches at each step, as the cell's model sees the logged configuration,
is :mod:`twinrl_data.contact_view`'s: points in 3D labelled with the two bodies, and a
plot per pair.

With two or more episodes (e.g. measured vs twin replay of one configuration) every
series is logged once per episode label under the same plot, so they overlay; every
cell after the first is drawn translucent, a ghost over the first, and a plot shows how
far each one's joints (rad) and TCP (mm) are from the first's at every step
(``signals/apart/...``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from twinrl_data import schema as contract
from twinrl_data.contact_view import Contact, log_contacts
from twinrl_data.errors import DataError
from twinrl_data.grasp_view import has_grasp, log_grasp
from twinrl_data.mcap_log import pose_groups
from twinrl_data.timeline import set_step, step_times

Pose = tuple[np.ndarray, np.ndarray]  # position xyz, quaternion wxyz, in the base frame


@dataclass(frozen=True)
class CellSteps:
    """The cell at every step of an episode: each moving body's positions (T, 3) and
    quaternions (T, 4, wxyz) by name, and what the robot touches at each step."""

    poses: dict[str, Pose]
    contacts: list[list[Contact]]


@dataclass(frozen=True)
class CameraMount:
    """Where a camera sits on a body of the cell, and how wide it sees."""

    body: str
    position: np.ndarray  # in the body's frame
    quaternion: np.ndarray  # wxyz; the camera looks along its -z, y up (MuJoCo's)
    fov_y_deg: float


class CellModel(Protocol):
    """A cell's geometry and its kinematics, supplied by the twin (this layer knows no
    robot model): see :class:`twinrl_sim.cell_view.TwinCell`."""

    def geometry(self, opacity: int = 255) -> dict[str, list[object]]:
        """Each drawn body's Rerun shapes in its own frame, by body name, at ``opacity``
        (0-255)."""

    def fixed_poses(self) -> dict[str, Pose]:
        """The poses of the drawn bodies that never move."""

    def cameras(self) -> dict[str, CameraMount]:
        """The cell's cameras by name."""

    def __call__(self, state: np.ndarray, environment: np.ndarray | None) -> dict[str, Pose]:
        """The moving bodies' poses at one step (its state and object-pose rows)."""

    def contacts(self, state: np.ndarray, environment: np.ndarray | None) -> list[Contact]:
        """What the robot's moving bodies touch at one step (no cell measures it)."""

    def steps(self, states: np.ndarray, environments: np.ndarray | None) -> CellSteps:
        """The poses and contacts of every step of an episode at once (its state rows
        and object-pose rows): what a saved view draws, the same as asking step by step."""


GHOST_ALPHA = 90  # opacity (of 255) of every cell after the first
EYE_OFFSET = np.array([1.1, -0.8, 0.6])  # m from the TCP's mean position to the 3D eye

COLORS = ([230, 120, 40], [40, 140, 230], [90, 190, 90], [200, 80, 200])
INTERVENTION_COLOR = [220, 30, 30]


def _names(episode: contract.Episode, key: str) -> list[str]:
    width = episode.data[key].shape[1]
    names = episode.meta.names.get(key) or []
    return names if len(names) == width else [f"{i}" for i in range(width)]


def _xyzw(wxyz: np.ndarray) -> list[float]:
    return [float(wxyz[1]), float(wxyz[2]), float(wxyz[3]), float(wxyz[0])]


def labels_for(episodes: Sequence[contract.Episode]) -> list[str]:
    """Short unique labels: ``world_source`` (plus an index when they repeat)."""
    base = [f"{e.meta.world}_{e.meta.source}" for e in episodes]
    return [b if base.count(b) == 1 else f"{b}_{i}" for i, b in enumerate(base)]


def log_episodes(
    episodes: Sequence[contract.Episode],
    recording: rr.RecordingStream,
    *,
    cell: CellModel | None = None,
) -> None:
    """Log ``episodes`` (overlaid on one timeline), each with ``cell`` in 3D when given,
    and send the blueprint."""
    labels = labels_for(episodes)
    rr.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, recording=recording)
    mounts = {} if cell is None else cell.cameras()
    touched = False
    for i, (color, label, episode) in enumerate(zip(COLORS * 4, labels, episodes, strict=False)):
        if cell is not None:
            opacity = GHOST_ALPHA if i > 0 else 255
            log_cell_geometry(cell, f"world/{label}/cell", recording, opacity)
            _log_frusta(episode, label, mounts, recording)
        _log_one(episode, label, color, recording, mounts)
        if cell is not None:
            touched |= _log_cell_steps(cell, episode, label, recording)
        log_grasp(episode, label, color, recording)
        if i > 0:
            _log_apart(episodes[0], episode, label, color, recording)
    recording.send_blueprint(_blueprint(episodes, labels, mounts, touched))


def _object_poses(episode: contract.Episode) -> np.ndarray | None:
    """The episode's object-pose rows, or None where it logs no object poses."""
    if contract.ENVIRONMENT_STATE not in episode.data:
        return None
    if not pose_groups(_names(episode, contract.ENVIRONMENT_STATE)):
        return None
    return episode.data[contract.ENVIRONMENT_STATE]


def _log_apart(
    first: contract.Episode,
    other: contract.Episode,
    label: str,
    color: list[int],
    recording: rr.RecordingStream,
) -> None:
    """How far ``other``'s joints (each, rad) and TCP (mm) are from ``first``'s, step by
    step over the steps both have."""
    names, other_names = _names(first, contract.STATE), _names(other, contract.STATE)
    joints = [n for n in names if n.startswith("q.") and n in other_names]
    tcp = [f"tcp.{axis}" for axis in "xyz"]
    has_tcp = all(n in names and n in other_names for n in tcp)
    a, b = first.data[contract.STATE], other.data[contract.STATE]
    columns = {n: (names.index(n), other_names.index(n)) for n in joints + (tcp if has_tcp else [])}
    for name in joints:
        rr.log(
            f"signals/apart/{name}/{label}",
            rr.SeriesLines(colors=[color], names=f"{name} {label}"),
            static=True,
            recording=recording,
        )
    if has_tcp:
        rr.log(
            f"signals/apart/tcp_mm/{label}",
            rr.SeriesLines(colors=[color], names=f"TCP mm {label}"),
            static=True,
            recording=recording,
        )
    for t in range(min(len(first), len(other))):
        recording.set_time("step", sequence=t)
        recording.set_time("time", duration=t / first.meta.fps)
        for name in joints:
            i, j = columns[name]
            rr.log(
                f"signals/apart/{name}/{label}",
                rr.Scalars(float(b[t, j] - a[t, i])),
                recording=recording,
            )
        if has_tcp:
            delta = [b[t, columns[n][1]] - a[t, columns[n][0]] for n in tcp]
            rr.log(
                f"signals/apart/tcp_mm/{label}",
                rr.Scalars(1000 * float(np.linalg.norm(delta))),
                recording=recording,
            )


def _image_path(label: str, camera: str, mounts: dict[str, CameraMount]) -> str:
    """Where a camera's images go: inside its frustum in the cell, or on their own."""
    if camera in mounts:
        return f"world/{label}/cell/{mounts[camera].body}/{camera}"
    return f"cameras/{label}/{camera}"


def _log_frusta(
    episode: contract.Episode,
    label: str,
    mounts: dict[str, CameraMount],
    recording: rr.RecordingStream,
) -> None:
    """Each mounted camera of the episode as a pinhole at its pose on its body."""
    for camera, frames in episode.images.items():
        if camera not in mounts or not len(frames):
            continue
        mount, (height, width) = mounts[camera], frames.shape[1:3]
        path = _image_path(label, camera, mounts)
        quat = rr.Quaternion(xyzw=_xyzw(mount.quaternion))
        rr.log(path, rr.Transform3D(translation=mount.position, quaternion=quat),
               static=True, recording=recording)  # fmt: skip
        rr.log(
            path,
            rr.Pinhole(
                fov_y=np.radians(mount.fov_y_deg),
                aspect_ratio=width / height,
                resolution=[width, height],
                camera_xyz=rr.ViewCoordinates.RUB,
                image_plane_distance=0.1,
            ),
            static=True,
            recording=recording,
        )


def _log_one(
    episode: contract.Episode,
    label: str,
    color: list[int],
    recording: rr.RecordingStream,
    mounts: dict[str, CameraMount],
) -> None:
    data = episode.data

    def log(path: str, value: object, static: bool = False) -> None:
        rr.log(path, value, static=static, recording=recording)

    state_names = _names(episode, contract.STATE)
    joints = [i for i, n in enumerate(state_names) if n.startswith("q.")]
    poses = pose_groups(state_names)
    env_poses = (
        pose_groups(_names(episode, contract.ENVIRONMENT_STATE))
        if contract.ENVIRONMENT_STATE in data
        else {}
    )
    intervention = data.get(contract.INTERVENTION, np.zeros(len(episode), bool))
    for name in (n for i, n in enumerate(state_names) if i in joints):
        log(
            f"signals/joints/{name}/{label}",
            rr.SeriesLines(colors=[color], names=f"{name} {label}"),
            static=True,
        )
    log(
        f"signals/intervention/{label}",
        rr.SeriesLines(colors=[INTERVENTION_COLOR], names="intervention"),
        static=True,
    )
    fps = episode.meta.fps
    times = step_times(len(episode), fps)

    def series(path: str, values: np.ndarray) -> None:
        rr.send_columns(path, indexes=times, columns=rr.Scalars.columns(scalars=values),
                        recording=recording)  # fmt: skip

    def poses_of(path: str, rows: np.ndarray, idx: list[int]) -> None:
        quats = rows[:, idx[3:]][:, [1, 2, 3, 0]]  # wxyz -> xyzw
        rr.send_columns(path, indexes=times, recording=recording,
                        columns=rr.Transform3D.columns(translation=rows[:, idx[:3]],
                                                       quaternion=quats))  # fmt: skip

    for t in range(len(episode)) if episode.images else ():  # a step at a time (memory)
        set_step(recording, t, fps)
        for camera, frames in episode.images.items():
            log(_image_path(label, camera, mounts), rr.Image(frames[t]))
    states = data[contract.STATE]
    for i in joints:
        series(f"signals/joints/{state_names[i]}/{label}", states[:, i])
    if contract.JOINT_TARGET in data:
        for j, values in enumerate(data[contract.JOINT_TARGET].T):
            name = state_names[joints[j]] if j < len(joints) else str(j)
            series(f"signals/joints/{name}/{label}_target", values)
    for j, values in enumerate(data[contract.ACTION].T):
        series(f"signals/actions/{j}/{label}_executed", values)
    if contract.ACTION_POLICY in data:
        for j, values in enumerate(data[contract.ACTION_POLICY].T):
            series(f"signals/actions/{j}/{label}_policy", values)
    for key, name in ((contract.REWARD, "reward"), (contract.SUCCESS, "success")):
        if key in data:
            series(f"signals/outcome/{name}/{label}", np.asarray(data[key], float))
    series(f"signals/intervention/{label}", np.asarray(intervention, float))
    # Where control changes hands (a run that starts with the person in control too).
    for t in np.flatnonzero(np.diff(np.asarray(intervention, int), prepend=0)):
        set_step(recording, t, fps)
        takes_over = bool(intervention[t])
        text = "human takes over" if takes_over else "policy in control"
        log(f"events/{label}", rr.TextLog(text, level="WARN" if takes_over else "INFO"))
    for frame, idx in poses.items():
        poses_of(f"world/{label}/{frame}", states, idx)
        log(f"world/{label}/{frame}/axes", rr.TransformAxes3D(0.05), static=True)
        if frame == "tcp":  # the whole path at once: growing it step by step is quadratic
            log(f"world/{label}/tcp_path", rr.LineStrips3D([states[:, idx[:3]]], colors=[color]),
                static=True)  # fmt: skip
    if env_poses:
        for frame, idx in env_poses.items():
            path = f"world/{label}/objects/{frame}"
            poses_of(path, data[contract.ENVIRONMENT_STATE], idx)
            log(f"{path}/marker", rr.Points3D([[0, 0, 0]], radii=0.01, colors=[color],
                                             labels=[frame]), static=True)  # fmt: skip


def _log_cell_steps(
    cell: CellModel, episode: contract.Episode, label: str, recording: rr.RecordingStream
) -> bool:
    """The cell's moving bodies and the robot's contacts at every step of ``episode``,
    each body's poses one column; whether it touched anything."""
    steps = cell.steps(episode.data[contract.STATE], _object_poses(episode))
    indexes = step_times(len(episode), episode.meta.fps)
    for body, (translations, quats) in steps.poses.items():
        rr.send_columns(
            f"world/{label}/cell/{body}",
            indexes=indexes,
            columns=rr.Transform3D.columns(
                translation=translations,
                quaternion=quats[:, [1, 2, 3, 0]],  # wxyz -> xyzw
            ),
            recording=recording,
        )
    return log_contacts(steps.contacts, episode.meta.fps, label, recording)


def log_cell_poses(
    cell: CellModel,
    root: str,
    state: np.ndarray,
    environment: np.ndarray | None,
    recording: rr.RecordingStream,
) -> None:
    """Where the cell's moving bodies are at the current time of ``recording``, from
    one step's state row (and object poses), under the entity ``root``."""
    for body, (pos, quat) in cell(state, environment).items():
        rr.log(
            f"{root}/{body}",
            rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=_xyzw(quat))),
            recording=recording,
        )


def log_cell_geometry(
    cell: CellModel, root: str, recording: rr.RecordingStream, opacity: int = 255
) -> None:
    """The cell's shapes under the entity ``root``, once (static), and where its fixed
    bodies are."""
    for body, shapes in cell.geometry(opacity).items():
        for i, shape in enumerate(shapes):
            rr.log(f"{root}/{body}/{i}", shape, static=True, recording=recording)
    for body, (pos, quat) in cell.fixed_poses().items():
        rr.log(
            f"{root}/{body}",
            rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=_xyzw(quat))),
            static=True,
            recording=recording,
        )


def _blueprint(
    episodes: Sequence[contract.Episode],
    labels: list[str],
    mounts: dict[str, CameraMount],
    touched: bool = False,
) -> rrb.Blueprint:
    cameras = [  # the whole image: Rerun's own bounds for a pinhole's view are a crop of it
        rrb.Spatial2DView(
            origin=_image_path(label, camera, mounts),
            name=f"{camera} ({label})",
            visual_bounds=rrb.VisualBounds2D(
                x_range=[0, frames.shape[2]], y_range=[0, frames.shape[1]]
            ),
        )
        for label, episode in zip(labels, episodes, strict=True)
        for camera, frames in episode.images.items()
    ]
    apart = (
        [
            rrb.TimeSeriesView(
                origin="signals/apart", name=f"apart from {labels[0]}: joints rad, TCP mm"
            )
        ]
        if len(episodes) > 1
        else []
    )
    grasp, force = [], []
    if any(has_grasp(e) for e in episodes):
        grasp = [rrb.TimeSeriesView(origin="signals/grasp", name="grasp: opening cm, in hand")]
    if any(contract.WRENCH in e.data for e in episodes):
        force = [rrb.TimeSeriesView(origin="signals/force", name="TCP force (N)")]
    if touched:
        force.append(rrb.TimeSeriesView(origin="signals/contacts", name="contacts (1: touching)"))
    plots = rrb.Vertical(
        rrb.TimeSeriesView(origin="signals/joints", name="joint positions and targets (rad)"),
        *apart,
        *grasp,
        *force,
        rrb.TimeSeriesView(origin="signals/actions", name="actions: executed vs policy"),
        rrb.TimeSeriesView(origin="signals/outcome", name="reward and success"),
        rrb.TimeSeriesView(origin="signals/intervention", name="interventions"),
    )
    scene = rrb.Spatial3DView(origin="world", name="scene", eye_controls=_eye(episodes[0]))
    columns = [scene, plots]
    if cameras:
        columns.insert(0, rrb.Vertical(*cameras))
    return rrb.Blueprint(
        rrb.Horizontal(*columns),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(expanded=False),
    )


def _eye(episode: contract.Episode) -> rrb.EyeControls3D | None:
    """The 3D view's eye: in front of the arm, to its right and above, on where the TCP
    went (Rerun's own pick from the whole scene looks along the table's edge)."""
    tcp = pose_groups(_names(episode, contract.STATE)).get("tcp")
    if tcp is None or not len(episode):
        return None
    target = episode.data[contract.STATE][:, tcp[:3]].mean(axis=0)
    return rrb.EyeControls3D(
        position=target + EYE_OFFSET, look_target=target, eye_up=[0.0, 0.0, 1.0]
    )


def save_rrd(
    episodes: Sequence[contract.Episode],
    path: str | Path,
    *,
    cell: CellModel | None = None,
    force: bool = False,
) -> Path:
    """Write ``episodes`` with their blueprint to an .rrd file."""
    path = Path(path)
    if path.exists() and not force:
        raise DataError(f"{path} already exists; choose another path or overwrite it (`force`)")
    recording = rr.RecordingStream("twinrl", recording_id=episodes[0].meta.episode_id)
    recording.save(str(path))
    log_episodes(episodes, recording, cell=cell)
    recording.flush()
    recording.disconnect()
    return path


def spawn_viewer(episodes: Sequence[contract.Episode], *, cell: CellModel | None = None) -> None:
    """Open the Rerun viewer on ``episodes``."""
    recording = rr.RecordingStream("twinrl", recording_id=episodes[0].meta.episode_id)
    recording.spawn()
    log_episodes(episodes, recording, cell=cell)
    recording.flush()
