"""Import joint logs recorded outside twinrl (CSV) as normal episodes.

Two readers share one code path:

- **Universal Robots RTDE** CSV, as UR's RTDE recorder (and ``ur_rtde``'s file
  recording) write it: ``timestamp``, ``target_q_0..5``, ``actual_q_0..5``,
  ``actual_qd_0..5``, ``target_moment_0..5``, ``actual_TCP_pose_0..5`` (x y z in m,
  then an axis-angle rotation in rad), delimited by commas, spaces or semicolons.
- **Generic** CSV with a small YAML column map (:class:`ColumnMap`): which column is
  time (and its unit), which columns hold the commanded and measured joint positions
  (rad or deg), optional velocities, torques and TCP pose; wide (one column per signal)
  or long (one value per line: time, signal name, value).

Rows are resampled onto a uniform clock (``fps``, default: the log's median rate) by
linear interpolation, since an episode is a sequence of equally spaced steps. What the
log does not hold stays missing: no gripper, no objects, no images, no rewards beyond
zeros. The executed end-effector ``action`` is the TCP motion between steps (from the
logged TCP pose or, when absent, from ``forward_kinematics`` of the measured joints).
"""

from __future__ import annotations

import csv
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import yaml

from twinrl_data import schema as contract
from twinrl_data.errors import DataError, DataWarning, SettingError

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
LAYOUTS = ("wide", "long")
DEFAULT_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")

ForwardKinematics = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``fk(q) -> (tcp xyz (m), tcp quaternion wxyz)`` for one row of joint positions."""


@dataclass(frozen=True)
class ColumnMap:
    """Where each signal lives in a CSV file (the YAML file of ``--map``)::

    time: t_ms            # column with the time stamps (may be left out with a rate)
    rate: 125             # optional: the log's sample rate (Hz); time = row / rate
    time_unit: ms         # s, ms, us or ns
    angle_unit: deg       # rad or deg (positions and velocities)
    layout: wide          # wide, or long: columns signal/value per line
    commanded: [cmd0, cmd1, cmd2, cmd3, cmd4, cmd5]
    measured: [q0, q1, q2, q3, q4, q5]
    velocity: [qd0, qd1, qd2, qd3, qd4, qd5]   # optional
    effort: [tau0, tau1, tau2, tau3, tau4, tau5]  # optional, N m
    effort_scale: [13.2, 13.2, 9.3, 4.6, 4.6, 4.6]  # optional: per joint, e.g. currents
                                                  # (A) times torque constants (N m/A)
    tcp: [x, y, z, rx, ry, rz]                    # optional, m + axis-angle rad
    joints: [shoulder_pan, ...]                   # optional names (default UR)
    signal_column: signal                         # long layout only
    value_column: value                           # long layout only
    """

    time: str | None
    commanded: list[str]
    measured: list[str]
    rate: float | None = None
    time_unit: str = "s"
    angle_unit: str = "rad"
    layout: str = "wide"
    velocity: list[str] = field(default_factory=list)
    effort: list[str] = field(default_factory=list)
    effort_scale: list[float] = field(default_factory=list)
    tcp: list[str] = field(default_factory=list)
    joints: list[str] = field(default_factory=lambda: list(DEFAULT_JOINTS))
    signal_column: str = "signal"
    value_column: str = "value"

    def __post_init__(self) -> None:
        problems = self._type_problems()
        if problems:
            raise DataError("column map: " + "; ".join(problems))
        if self.rate is not None and not (
            isinstance(self.rate, int | float) and math.isfinite(self.rate) and 0 < self.rate <= 1e5
        ):
            problems.append(f"rate must be a sample rate in Hz (0 to 100000), got {self.rate!r}")
        if self.time is None and self.rate is None:
            problems.append("give the time column (time) or the log's sample rate (rate)")
        if self.rate is not None and self.layout == "long":
            problems.append("rate applies to the wide layout (one row per sample)")
        if self.time_unit not in TIME_UNITS:
            problems.append(f"time_unit must be one of {', '.join(TIME_UNITS)}")
        if self.angle_unit not in ANGLE_UNITS:
            problems.append(f"angle_unit must be rad or deg, got '{self.angle_unit}'")
        if self.layout not in LAYOUTS:
            problems.append(f"layout must be wide or long, got '{self.layout}'")
        n = len(self.joints)
        for name in ("commanded", "measured", "velocity", "effort"):
            columns = getattr(self, name)
            if (columns or name in ("commanded", "measured")) and len(columns) != n:
                problems.append(f"{name} needs {n} columns (one per joint), got {len(columns)}")
        if self.effort_scale and len(self.effort_scale) != len(self.effort):
            problems.append(
                f"effort_scale needs one factor per effort column ({len(self.effort)}), "
                f"got {len(self.effort_scale)}"
            )
        if self.tcp and len(self.tcp) != 6:
            problems.append(f"tcp needs 6 columns (x y z rx ry rz), got {len(self.tcp)}")
        if problems:
            raise DataError("column map: " + "; ".join(problems))

    def _type_problems(self) -> list[str]:
        """Fields of the wrong type (a YAML file can hold anything)."""
        problems = []
        for name in ("commanded", "measured", "velocity", "effort", "tcp", "joints"):
            value = getattr(self, name)
            if not isinstance(value, list | tuple) or not all(isinstance(c, str) for c in value):
                problems.append(f"{name} must be a list of column names, got {value!r}")
        for name in ("time", "time_unit", "angle_unit", "layout", "signal_column", "value_column"):
            value = getattr(self, name)
            if not (isinstance(value, str) or (name == "time" and value is None)):
                problems.append(f"{name} must be a name, got {value!r}")
        scale = self.effort_scale
        if not isinstance(scale, list | tuple) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in scale
        ):
            problems.append(f"effort_scale must be a list of numbers, got {scale!r}")
        if self.rate is not None and (
            isinstance(self.rate, bool) or not isinstance(self.rate, int | float)
        ):
            problems.append(f"rate must be a number (Hz), got {self.rate!r}")
        return problems

    @classmethod
    def load(cls, path: str | Path) -> ColumnMap:
        """Read a column map YAML file; unknown keys are an error."""
        path = Path(path)
        if not path.is_file():
            raise DataError(f"column map {path} does not exist")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            raise DataError(f"{path}: not valid YAML ({err})") from None
        if not isinstance(data, dict):
            raise DataError(
                f"{path}: a column map is a YAML mapping of episode fields to CSV "
                "columns (see the episode-log guide)"
            )
        unknown = sorted(set(data) - set(cls.__dataclass_fields__))
        if unknown:
            raise DataError(
                f"{path}: unknown key(s) {unknown}; known: {sorted(cls.__dataclass_fields__)}"
            )
        missing = [k for k in ("commanded", "measured") if k not in data]
        if "time" not in data and "rate" not in data:
            missing.append("time (or rate)")
        if missing:
            raise DataError(f"{path}: missing key(s) {missing}")
        try:
            return cls(**{"time": None} | data)
        except ValueError as err:
            raise DataError(f"{path}: {err}") from None


MAX_VALUE = 1e6  # no logged angle, speed, torque or position is larger
TcpFrame = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``(positions (n, 3), quaternions wxyz (n, 4)) -> the same in another TCP frame``."""

RTDE_MAP = ColumnMap(
    time="timestamp",
    commanded=[f"target_q_{i}" for i in range(6)],
    measured=[f"actual_q_{i}" for i in range(6)],
    velocity=[f"actual_qd_{i}" for i in range(6)],
    effort=[f"target_moment_{i}" for i in range(6)],
    tcp=[f"actual_TCP_pose_{i}" for i in range(6)],
)
"""UR's RTDE recorder columns, torques from ``target_moment_*`` (see :func:`rtde_map`)."""

TORQUE_SOURCES = ("auto", "target_moment", "current_as_torque", "current", "none")


def rtde_map(
    path: str | Path, torque: str = "auto", torque_constants: list[float] | None = None
) -> tuple[ColumnMap, str]:
    """The RTDE column map for the log at ``path``, and a sentence naming its torques.

    A UR logs its joint torques in up to three ways: ``target_moment`` (N m, the torque
    its joint controllers command: the arm's model with the payload set on the
    controller, what the twin's feed-forward servos log), ``actual_current_as_torque``
    (N m, the measured motor currents converted by the controller; PolyScope 5.23 and
    later) and ``actual_current`` (A, which need the drives' torque constants). ``auto``
    takes the first the log has; without any, the episodes carry no torques.
    """
    if torque not in TORQUE_SOURCES:
        raise SettingError("torque", f"must be one of {', '.join(TORQUE_SOURCES)}, got '{torque}'")
    header = _header(Path(path))
    columns = {
        "target_moment": [f"target_moment_{i}" for i in range(6)],
        "current_as_torque": [f"actual_current_as_torque_{i}" for i in range(6)],
        "current": [f"actual_current_{i}" for i in range(6)],
    }
    if torque_constants is not None and len(torque_constants) != 6:
        raise SettingError(
            "torque_constants",
            f"needs 6 numbers (N m/A, one per joint), got {len(torque_constants)}",
        )
    if torque == "auto":
        present = [k for k in ("target_moment", "current_as_torque") if set(columns[k]) <= header]
        if not present and torque_constants is not None and set(columns["current"]) <= header:
            present = ["current"]
        torque = present[0] if present else "none"
    if torque == "current" and torque_constants is None:
        raise SettingError(
            "torque", "current needs the drives' torque constants (torque_constants, N m/A)"
        )
    if torque == "none":
        return replace(RTDE_MAP, effort=[]), (
            "no joint torques (the log has neither target_moment nor actual_current_as_torque)"
        )
    missing = sorted(set(columns[torque]) - header)
    if missing:
        raise DataError(f"{path}: torque {torque} needs column(s) {missing}; the log lacks them")
    described = {
        "target_moment": "target_moment (N m: the torques the controller commands)",
        "current_as_torque": "actual_current_as_torque (N m: the measured currents)",
        "current": "actual_current (A) times the given torque constants",
    }[torque]
    scale = list(torque_constants) if torque == "current" else []
    cmap = replace(RTDE_MAP, effort=columns[torque], effort_scale=scale)
    return cmap, f"joint torques from {described}"


def _delimiter(path: Path) -> str:
    with path.open(newline="") as f:
        header = f.readline()
    if not header.strip():
        raise DataError(f"{path} is empty")
    try:
        return csv.Sniffer().sniff(header, delimiters=",; \t").delimiter
    except csv.Error:
        return ","


def _header(path: Path) -> set[str]:
    """The column names of a CSV file."""
    if not path.is_file():
        raise DataError(f"CSV file {path} does not exist")
    with path.open(newline="") as f:
        return {c.strip() for c in next(csv.reader(f, delimiter=_delimiter(path)), [])}


def read_table(path: str | Path) -> pa.Table:
    """The CSV as an Arrow table (delimiter sniffed from the header line)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"CSV file {path} does not exist")
    parse = pacsv.ParseOptions(delimiter=_delimiter(path))
    try:
        return pacsv.read_csv(path, parse_options=parse)
    except pa.ArrowInvalid as err:
        raise DataError(f"{path}: not a readable CSV ({str(err).splitlines()[0]})") from None


def _columns(table: pa.Table, columns: list[str], path: Path) -> dict[str, np.ndarray]:
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        shown = ", ".join(table.column_names[:12]) + (" ..." if table.num_columns > 12 else "")
        raise DataError(f"{path}: column(s) {missing} not found; the file has: {shown}")
    out = {}
    for c in columns:
        try:
            out[c] = table.column(c).to_numpy(zero_copy_only=False).astype(float)
        except (pa.ArrowInvalid, ValueError):
            raise DataError(f"{path}: column '{c}' is not numeric") from None
    return out


def _signals(
    table: pa.Table, cmap: ColumnMap, path: Path
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(time in s, column -> values on that time base), from a wide or long table."""
    wanted = [*cmap.commanded, *cmap.measured, *cmap.velocity, *cmap.effort, *cmap.tcp]
    if cmap.layout == "wide":
        values = _columns(table, [c for c in (cmap.time, *wanted) if c is not None], path)
        if cmap.time is None:
            return np.arange(table.num_rows, dtype=float), values  # the rate gives time
        return values.pop(cmap.time) * TIME_UNITS[cmap.time_unit], values
    need = [cmap.time, cmap.signal_column, cmap.value_column]
    missing = [c for c in need if c not in table.column_names]
    if missing:
        raise DataError(f"{path}: long layout needs columns {need}; missing {missing}")
    times = _columns(table, [cmap.time], path)[cmap.time]
    values = _columns(table, [cmap.value_column], path)[cmap.value_column]
    names = np.asarray(table.column(cmap.signal_column).to_pylist(), dtype=object).astype(str)
    grid = np.unique(times)
    out = {}
    for signal in wanted:
        rows = names == signal
        if not rows.any():
            raise DataError(
                f"{path}: signal '{signal}' has no rows in column '{cmap.signal_column}'"
            )
        t, v = times[rows], values[rows]
        order = np.argsort(t)
        out[signal] = np.interp(grid, t[order], v[order])
    return grid * TIME_UNITS[cmap.time_unit], out


def _rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    axis = np.divide(rotvec, angle, out=np.zeros_like(rotvec), where=angle > 1e-12)
    return np.concatenate([np.cos(angle / 2), axis * np.sin(angle / 2)], axis=-1)


def _relative_rotvec(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Axis-angle of q1 * conj(q0) per row (wxyz quaternions), in the base frame."""
    w0, v0 = q0[:, :1], -q0[:, 1:]
    w1, v1 = q1[:, :1], q1[:, 1:]
    w = w1 * w0 - np.sum(v1 * v0, axis=1, keepdims=True)
    v = w1 * v0 + w0 * v1 + np.cross(v1, v0)
    sign = np.where(w < 0, -1.0, 1.0)
    w, v = w * sign, v * sign
    s = np.linalg.norm(v, axis=1, keepdims=True)
    angle = 2 * np.arctan2(s, w)
    return np.divide(v * angle, s, out=np.zeros_like(v), where=s > 1e-12)


def _without_repeats(
    times: np.ndarray, values: dict[str, np.ndarray], path: Path
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The rows without the copies a file recorder writes, saying how many it dropped.

    ur_rtde's file recording writes a row per period of its own, not per package: a row
    repeats the one before exactly (stamp and values) when no new package came in
    between, and a row read while the next package arrived mixes the two (a stamp shared
    with a neighbour, each value either that neighbour's or the row's on its other
    side). Neither is a new sample. A row read as a package arrived may also carry the
    last package's stamp with every value new, the next row two periods on or more (the
    recorder misses packages now and then): it is the package after the last one, and
    takes its stamp back. A clock coarser than the rows (every row's values new, the stamps
    not skipping) is none of these, and is left to :func:`_clock`."""
    table = np.column_stack([times, *values.values()])
    exact = np.flatnonzero(np.all(table[1:] == table[:-1], axis=1)) + 1
    keep = np.ones(len(times), bool)
    keep[exact] = False
    table = table[keep]
    values_of = table[:, 1:]

    def mixes(row: int, a: int, b: int) -> bool:  # each value is row a's or row b's
        inside = 0 <= a < len(table) and 0 <= b < len(table)
        return inside and bool(
            np.all((values_of[row] == values_of[a]) | (values_of[row] == values_of[b]))
        )

    steps = np.diff(table[:, 0])
    tick = float(np.median(steps[steps > 0])) if (steps > 0).any() else 0.0
    torn, restamped = [], {}
    for i in np.flatnonzero(steps == 0):  # rows i and i+1 share a stamp
        if mixes(i + 1, i, i + 2):
            torn.append(i + 1)  # this stamp, partly the next package's values
        elif mixes(i, i - 1, i + 1):
            torn.append(i)  # the next stamp, partly the last package's values
        elif i + 2 < len(table) and table[i + 2, 0] - table[i, 0] > 2 * tick - tick / 100:
            # Every value new and the next row two periods on or more: the package after
            # the last one, under the last one's stamp; it takes the stamp it lacks.
            restamped[i + 1] = table[i, 0] + tick
    if not len(exact) and not torn and not restamped:
        return times, values
    rows = np.flatnonzero(keep)
    times = times.copy()
    for row, stamp in restamped.items():
        times[rows[row]] = stamp
    keep[rows[torn]] = False
    warnings.warn(
        f"{path}: dropped {len(exact)} of {len(times)} rows that repeat the row before "
        f"exactly and {len(torn)} that mix two packages under one stamp, and gave "
        f"{len(restamped)} the stamp between their neighbours' (the last package's "
        "stamp with new values): a file recorder writing on its own clock, as ur_rtde's does",
        DataWarning,
        stacklevel=3,
    )
    return times[keep], {c: v[keep] for c, v in values.items()}


def _clock(times: np.ndarray, cmap: ColumnMap, path: Path) -> np.ndarray:
    """Each row's time (s, from 0): from the log's rate and the row index when the column
    map gives one, else from the stamps, which must advance at every row (a row is never
    dropped: repeated or backward stamps are an error that says what to do)."""
    if len(times) < 2:
        raise DataError(f"{path}: needs at least two rows, got {len(times)}")
    if cmap.rate is not None:
        return np.arange(len(times)) / cmap.rate
    steps = np.diff(times)
    stuck = int((steps == 0).sum())
    backward = int((steps < 0).sum())
    if stuck or backward:
        tick = np.median(steps[steps > 0]) if (steps > 0).any() else 0.0
        what = []
        if stuck:
            what.append(f"{stuck} of {len(times)} rows repeat the stamp of the row before")
        if backward:
            what.append(f"{backward} rows go back in time")
        coarse = f" (the clock ticks every {tick:g} s, coarser than the rows)" if stuck else ""
        raise DataError(
            f"{path}: {' and '.join(what)}{coarse}; no row is dropped: give the log's sample "
            "rate in the column map (rate: 125) to take time from the row index"
        )
    return times - times[0]  # relative: epoch stamps lose precision in arithmetic


def import_csv(
    path: str | Path,
    cmap: ColumnMap = RTDE_MAP,
    *,
    fps: float | None = None,
    task: str = "arm",
    robot: str = "ur5e",
    world: str = "real",
    config: dict[str, Any] | None = None,
    forward_kinematics: ForwardKinematics | None = None,
    tcp_frame: TcpFrame | None = None,
) -> contract.Episode:
    """One CSV log as an episode of source ``imported`` on a uniform ``fps`` clock.

    ``tcp_frame`` maps a logged TCP pose (the controller's configured TCP in its base
    frame) into the twin's TCP frame, so that the log and the twin compare one point."""
    path = Path(path)
    times, values = _signals(read_table(path), cmap, path)
    for column, column_values in {cmap.time or "time": times, **values}.items():
        limit = np.inf if column == (cmap.time or "time") else MAX_VALUE  # epoch stamps
        bad = np.flatnonzero(~np.isfinite(column_values) | (np.abs(column_values) > limit))
        if len(bad):
            more = f" (and {len(bad) - 1} more rows)" if len(bad) > 1 else ""
            raise DataError(
                f"{path}: column {column} has a missing, non-numeric or absurd value in data "
                f"row {bad[0] + 1}{more}; fix or drop those rows"
            )
    if cmap.time is not None:
        times, values = _without_repeats(times, values, path)
    times = _clock(times, cmap, path)
    rate = float(f"{1.0 / float(np.median(np.diff(times))):.4g}")  # 125 Hz, not 124.99998
    fps = float(fps or rate)
    if not fps > 0:
        raise SettingError("fps", f"must be positive, got {fps}")
    clock = np.arange(0.0, times[-1] + 1e-9, 1.0 / fps)
    if abs(fps - rate) > 1e-3 * rate:
        kind = (
            f"motion faster than {fps / 2:g} Hz is lost"
            if fps < rate
            else ("the steps between rows are interpolated, not measured")
        )
        warnings.warn(
            f"{path}: resampled from {rate:g} Hz to {fps:g} Hz ({len(times)} rows became "
            f"{len(clock)} steps); {kind}",
            DataWarning,
            stacklevel=2,
        )
    at = {c: np.interp(clock, times, v) for c, v in values.items()}
    angle = ANGLE_UNITS[cmap.angle_unit]
    stack = lambda cols, scale=1.0: np.stack([at[c] for c in cols], axis=1) * scale  # noqa: E731

    q = stack(cmap.measured, angle)
    names = {contract.JOINT_TARGET: [f"q.{j}" for j in cmap.joints]}
    state_names = [f"q.{j}" for j in cmap.joints]
    parts = [q]
    if cmap.velocity:
        parts.append(stack(cmap.velocity, angle))
        state_names += [f"qd.{j}" for j in cmap.joints]
    if cmap.tcp:
        pose = stack(cmap.tcp)
        tcp_pos, tcp_quat = pose[:, :3], _rotvec_to_quat(pose[:, 3:])
        if tcp_frame is not None:
            tcp_pos, tcp_quat = tcp_frame(tcp_pos, tcp_quat)
    elif forward_kinematics is not None:
        poses = [forward_kinematics(row) for row in q]
        tcp_pos = np.array([p for p, _ in poses])
        tcp_quat = np.array([r for _, r in poses])
    else:
        raise DataError(
            f"{path}: the TCP pose is neither logged nor computable; give tcp columns "
            "in the column map or a robot model for forward kinematics"
        )
    parts += [tcp_pos, tcp_quat]
    state_names += ["tcp.x", "tcp.y", "tcp.z", "tcp.qw", "tcp.qx", "tcp.qy", "tcp.qz"]
    moves = np.diff(tcp_pos, axis=0, append=tcp_pos[-1:])
    turns = _relative_rotvec(tcp_quat, np.concatenate([tcp_quat[1:], tcp_quat[-1:]]))
    action = np.concatenate([moves, turns, np.zeros((len(clock), 1))], axis=1)
    names[contract.STATE] = state_names
    names[contract.ACTION] = ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]
    n = len(clock)
    data = {
        contract.STATE: np.concatenate(parts, axis=1).astype(np.float32),
        contract.ACTION: action.astype(np.float32),
        contract.JOINT_TARGET: stack(cmap.commanded, angle).astype(np.float32),
        contract.INTERVENTION: np.zeros(n, bool),
        contract.REWARD: np.zeros(n, np.float32),
        contract.DONE: np.arange(n) == n - 1,
        contract.SUCCESS: np.zeros(n, bool),
    }
    if cmap.effort:
        effort = stack(cmap.effort) * (np.asarray(cmap.effort_scale) if cmap.effort_scale else 1.0)
        data[contract.EFFORT] = effort.astype(np.float32)
        names[contract.EFFORT] = contract.effort_names(cmap.joints)
    meta = contract.EpisodeMeta(
        task=task,
        source="imported",
        world=world,
        config=config or {"initial_q": q[0].tolist()},
        fps=fps,
        robot=robot,
        names=names,
        policy=f"csv:{path.name}",
    )
    for key, array in data.items():
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise DataError(f"{path}: {key} comes out non-finite; check the log's values")
    return contract.Episode(meta, data)
