"""Shooting windows cut from measured episodes, and where each one starts in the twin.

A window is ``W`` consecutive control periods of one episode: the measurement at its
first row is where the twin restarts (arm joints and velocities, gripper opening,
object poses; a resting object's position is the mean over its rest, since a
tracker's millimetre of noise would otherwise start it inside the table or the
fingers), the logged joint targets and gripper commands are re-sent, and the
measurement at every later row is compared.

In a log faster than the servos settle (a controller's 125 or 500 Hz), the arm's start
is estimated from the rows around it (:func:`smoothed_start`) rather than read from one
row: a stiff servo turns an encoder's noise at the start into a torque transient (a UR's
16,000 N m/rad shoulder loop makes 0.2 mrad of noise 3 N m, sixty times a torque
estimate's noise) that no effect explains. Localisation and identification replay
the same windows through the one engine (:mod:`twinrl_sim.windowed`), so both measure
the same residual.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import mujoco
import numpy as np

from twinrl_data import schema as contract
from twinrl_sim.effects import torque_offset
from twinrl_sim.errors import TwinError
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.layout import CellLayout
from twinrl_sim.robots import gripper as gripper_lib
from twinrl_sim.servo import servo_lead, tracking_setpoints
from twinrl_sim.windowed import INPUTS, STATE, Starts, WindowedReplay, control_substeps

DELAY_HISTORY = 0.3  # s: the longest actuator delay a fit can reach
HELD_TOLERANCE = 1e-4  # rad: targets this close to the first are a log's start at rest
WINDOW_SECONDS = 2.0  # a shooting window's default length: 20 steps at 10 Hz, 250 at 125 Hz
START_SPAN = 0.1  # s either side of a window's start whose rows estimate the arm's state there
START_DEGREE = 3  # degree of the polynomial in time fitted to those rows


@dataclass
class Windows:
    """Shooting windows cut from measured episodes (``n`` windows, ``W`` rows each).

    Row 0 of a window is its measured start; rows 1..W are compared.
    """

    names: list[str]  # compared signals: q.*, qd.*, tcp.x/y/z, tau.*, <object>.x/y/z
    families: list[str]  # NoiseFloor field of each signal
    objects: list[str]  # objects whose poses are in objects0 (scene order)
    measured: np.ndarray  # (n, W, n_signals), rows 1..W
    q0: np.ndarray  # (n, n_arm)
    qd0: np.ndarray  # (n, n_arm)
    opening0: np.ndarray  # (n,) gripper opening (m)
    objects0: np.ndarray  # (n, n_objects, 7) object poses (xyz, wxyz) at the start
    targets: np.ndarray  # (n, W, n_arm) joint targets sent during rows 0..W-1
    gripper: np.ndarray  # (n, W) gripper commands sent during rows 0..W-1
    history: np.ndarray  # (n, H, n_arm) targets of the H control periods before row 0
    episode: np.ndarray  # (n,) index of the episode each window comes from
    start: np.ndarray  # (n,) row of the episode at which it starts
    fps: float

    def __len__(self) -> int:
        return len(self.q0)

    def subset(self, index: np.ndarray) -> Windows:
        arrays = {f.name: getattr(self, f.name)[index] for f in fields(self) if f.name in ARRAYS}
        return Windows(self.names, self.families, self.objects, **arrays, fps=self.fps)

    @property
    def rows(self) -> int:
        return self.measured.shape[1]

    @property
    def grasping(self) -> bool:
        """Whether the gripper is closed in any window (object effects act then)."""
        return bool((self.gripper > 0.5).any())


ARRAYS = (
    "measured",
    "q0",
    "qd0",
    "opening0",
    "objects0",
    "targets",
    "gripper",
    "history",
    "episode",
    "start",
)


def _object_columns(episode: contract.Episode, objects: Sequence[str]) -> list[int] | None:
    names = episode.meta.names.get(contract.ENVIRONMENT_STATE, [])
    wanted = [f"{o}.{c}" for o in objects for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
    if not objects or contract.ENVIRONMENT_STATE not in episode.data:
        return None
    if not set(wanted) <= set(names):
        return None
    return [names.index(n) for n in wanted]


def cut_windows(
    episodes: Sequence[contract.Episode],
    layout: CellLayout,
    objects: Sequence[str],
    *,
    window: int | None = None,
    cover_tail: bool = False,
    noise: NoiseFloor | None = None,
) -> Windows:
    """Cut every episode into consecutive windows of ``window`` compared rows (default:
    :data:`WINDOW_SECONDS` of the log), at the episodes' own control rate (one rate for
    all). The default is a duration, not a count of rows: the same 20 rows are 2 s at
    10 Hz but 0.16 s at 125 Hz, too short for a delay and a soft servo to look
    different (a 125 Hz log's hidden delay was then taken for a servo gain).

    A tail shorter than a window is left out, or, with ``cover_tail``, compared by one
    more window that ends at the episode's last row (its first rows repeat the previous
    window's). Signals are those every episode has: joint angles and velocities and the
    TCP position always; joint torques when all episodes log ``observation.effort``;
    object positions when all log them. ``noise`` weighs joint angles against velocities
    in the start estimate (:func:`smoothed_start`).
    """
    noise = noise or NoiseFloor()
    arm = layout.arm_joints
    for episode in episodes:
        _check_episode(episode, arm)
    rates = sorted({e.meta.fps for e in episodes})
    if len(rates) > 1:
        raise TwinError(
            f"the episodes were logged at different rates ({', '.join(f'{r:g}' for r in rates)} "
            "Hz); compare episodes of one rate at a time"
        )
    control_hz = rates[0] if rates else 1.0
    if window is None:
        window = max(2, round(WINDOW_SECONDS * control_hz))
    if window < 2:
        raise TwinError(f"a shooting window needs at least 2 control steps, got {window}")
    with_tau = all(contract.EFFORT in e.data for e in episodes)
    object_cols = [_object_columns(e, objects) for e in episodes]
    with_objects = bool(objects) and all(c is not None for c in object_cols)
    names = [f"q.{j}" for j in arm] + [f"qd.{j}" for j in arm] + ["tcp.x", "tcp.y", "tcp.z"]
    families = ["q"] * len(arm) + ["qd"] * len(arm) + ["tcp"] * 3
    if with_tau:
        names += contract.effort_names(arm)
        families += ["tau"] * len(arm)
    manipulated = [o for o in objects if o in layout.manipulated] if with_objects else []
    for o in manipulated:
        names += [f"{o}.x", f"{o}.y", f"{o}.z"]
        families += ["object"] * 3
    history_steps = math.ceil(DELAY_HISTORY * control_hz) + 1
    parts: dict[str, list] = {k: [] for k in ARRAYS}
    for e_index, episode in enumerate(episodes):
        state_names = episode.meta.names[contract.STATE]
        col = {n: i for i, n in enumerate(state_names)}
        state = episode.data[contract.STATE].astype(float)
        q = state[:, [col[f"q.{j}"] for j in arm]]
        qd = state[:, [col[f"qd.{j}"] for j in arm]]
        tcp = state[:, [col[n] for n in ("tcp.x", "tcp.y", "tcp.z")]]
        opening = (
            state[:, col["gripper.opening"]]
            if "gripper.opening" in col
            else np.full(len(state), 2 * gripper_lib.STROKE)
        )
        actions = episode.data.get(contract.ACTION)
        gripper = np.zeros(len(state)) if actions is None else np.clip(actions[:, 6], 0, 1)
        signals = [q, qd, tcp]
        if with_tau:
            signals.append(_effort(episode, arm))
        if with_objects:
            env = episode.data[contract.ENVIRONMENT_STATE].astype(float)[:, object_cols[e_index]]
            poses = env.reshape(len(env), len(objects), 7)
            for o in manipulated:
                signals.append(poses[:, list(objects).index(o), :3])
            movable = [o in layout.manipulated for o in objects]
            start_poses = _rest_averaged(poses, gripper, movable)
        else:
            start_poses = np.zeros((len(state), 0, 7))
        measured = np.hstack(signals)
        targets = episode.data[contract.JOINT_TARGET].astype(float)
        starts = list(range(0, len(state) - window, window))
        if cover_tail and len(state) > window and (len(state) - 1) % window:
            starts.append(len(state) - 1 - window)
        q_start, qd_start = smoothed_start(q, qd, starts, control_hz, noise)
        # Before the first row the servos held where the arm stood.
        held = _held_before(q_start[0] if starts else q[0], targets)  # starts[0] is row 0
        padded = np.vstack([np.repeat(held[None], history_steps, 0), targets])
        for k, start in enumerate(starts):
            parts["measured"].append(measured[start + 1 : start + window + 1])
            parts["q0"].append(q_start[k])
            parts["qd0"].append(qd_start[k])
            parts["opening0"].append(opening[start])
            parts["objects0"].append(start_poses[start])
            parts["targets"].append(targets[start : start + window])
            parts["gripper"].append(gripper[start : start + window])
            parts["history"].append(padded[start : start + history_steps])
            parts["episode"].append(e_index)
            parts["start"].append(start)
    if not parts["q0"]:
        raise TwinError(
            f"no episode is longer than one shooting window ({window} steps); record "
            "longer episodes or use a smaller window"
        )
    arrays = {k: np.asarray(v) for k, v in parts.items()}
    objects_logged = list(objects) if with_objects else []
    return Windows(names, families, objects_logged, **arrays, fps=control_hz)


def smoothed_start(
    q: np.ndarray, qd: np.ndarray, rows: Sequence[int], fps: float, noise: NoiseFloor
) -> tuple[np.ndarray, np.ndarray]:
    """The arm's joint angles and velocities at ``rows`` of one episode, (len(rows),
    n_arm) each, estimated from the rows within :data:`START_SPAN` of each.

    A polynomial in time of degree :data:`START_DEGREE` is fitted per joint, by least
    squares, to the angles and to the velocities (its derivative) of those rows, each
    weighed by its noise; its value and slope at the row are the estimate. In a 125 Hz
    log this cuts a start's angle noise several-fold, where one row's noise would start
    a stiff servo with a torque transient. A log too slow for that (fewer than two rows
    either side within the span, as at 10 Hz) keeps each row's measurement."""
    rows = np.asarray(rows, int)
    span = round(START_SPAN * fps)
    if span < 2 or not len(rows):
        return q[rows].copy(), qd[rows].copy()
    powers = np.arange(START_DEGREE + 1)
    q_start, qd_start = np.empty((len(rows), q.shape[1])), np.empty((len(rows), q.shape[1]))
    for k, row in enumerate(rows):
        lo, hi = max(0, row - span), min(len(q), row + span + 1)
        t = (np.arange(lo, hi) - row) / fps
        value = t[:, None] ** powers
        slope = powers * t[:, None] ** np.maximum(powers - 1, 0)
        design = np.vstack([value / noise.q, slope / noise.qd])
        observed = np.vstack([q[lo:hi] / noise.q, qd[lo:hi] / noise.qd])
        coefficients = np.linalg.lstsq(design, observed, rcond=None)[0]
        q_start[k], qd_start[k] = coefficients[0], coefficients[1]
    return q_start, qd_start


def _held_before(q0: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Where the servos held the arm before an episode's first row, whose estimated
    joint angles are ``q0``. A log that starts at rest (its second target within
    :data:`HELD_TOLERANCE` of the first) held its first target; one that starts moving,
    where the arm stood. (One row's measurement there would bring its sensor noise: over
    a 2 ms period, a spurious speed that a tracking servo's lead turns into tens of N m
    in a 500 Hz log's first rows; a delay holds it for the delay's length.)"""
    at_rest = len(targets) < 2 or np.abs(targets[1] - targets[0]).max() <= HELD_TOLERANCE
    return targets[0] if at_rest else q0


REST_SPREAD = 5.0  # robust deviations (per axis) within which a row counts as at rest


def _rest_averaged(poses: np.ndarray, gripper: np.ndarray, movable: list[bool]) -> np.ndarray:
    """Object poses (T, n, 7) with the position of every row at which an object rests
    replaced by its mean over that rest.

    A fixture (not ``movable``) rests all episode; a movable object rests in runs of
    rows with the gripper open. Rows further than :data:`REST_SPREAD` robust
    deviations from their rest's median (a bump, the settling after a release) keep
    their own measurement.
    """
    averaged = poses.copy()
    closed = gripper > 0.5
    edges = np.flatnonzero(np.diff(closed.astype(int))) + 1
    everything = np.arange(len(poses))
    for k, moves in enumerate(movable):
        rests = (
            [r for r in np.split(everything, edges) if not closed[r[0]]] if moves else [everything]
        )
        for run in rests:
            xyz = poses[run, k, :3]
            middle = np.median(xyz, axis=0)
            spread = 1.4826 * np.median(np.abs(xyz - middle), axis=0)
            still = np.all(np.abs(xyz - middle) <= REST_SPREAD * spread, axis=1)
            if still.sum() > 1:
                averaged[run[still], k, :3] = xyz[still].mean(axis=0)
    return averaged


def _effort(episode: contract.Episode, arm: Sequence[str]) -> np.ndarray:
    names = episode.meta.names.get(contract.EFFORT) or contract.effort_names(arm)
    col = {n: i for i, n in enumerate(names)}
    missing = [j for j in arm if f"tau.{j}" not in col]
    if missing:
        raise TwinError(
            f"episode {episode.meta.episode_id}: observation.effort lacks tau.{missing[0]}"
        )
    return episode.data[contract.EFFORT].astype(float)[:, [col[f"tau.{j}"] for j in arm]]


def _check_episode(episode: contract.Episode, arm: Sequence[str]) -> None:
    ident = episode.meta.episode_id
    if contract.JOINT_TARGET not in episode.data:
        raise TwinError(
            f"episode {ident} has no command.joint_target; the gap workflow re-sends the "
            "joint targets that were logged"
        )
    names = episode.meta.names.get(contract.STATE, [])
    missing = [n for j in arm for n in (f"q.{j}", f"qd.{j}") if n not in names]
    missing += [n for n in ("tcp.x", "tcp.y", "tcp.z") if n not in names]
    if missing:
        raise TwinError(f"episode {ident} lacks {missing[0]} in observation.state")


def place_measured(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    layout: CellLayout,
    objects: Sequence[str],
    poses: np.ndarray,
    opening: float,
) -> None:
    """Put ``objects`` at measured ``poses`` (n, 7: xyz, wxyz; NaN: not measured, left
    alone) — free bodies in ``qpos``, fixtures as mocap inputs — and the gripper's
    fingers at the measured ``opening`` (m)."""
    for name, pose in zip(objects, poses, strict=True):
        if np.isnan(pose).any():
            continue
        body = model.body(name)
        if body.mocapid[0] >= 0:
            data.mocap_pos[body.mocapid[0]] = pose[:3]
            data.mocap_quat[body.mocapid[0]] = pose[3:]
        else:
            adr = model.joint(f"{name}_free").qposadr[0]
            data.qpos[adr : adr + 7] = pose
    if layout.gripper_joint:
        fingers = [model.joint(j).qposadr[0] for j in (gripper_lib.JOINT, gripper_lib.MIRROR_JOINT)]
        data.qpos[fingers] = gripper_lib.joint_from_opening(opening)


def measured_starts(model: mujoco.MjModel, layout: CellLayout, windows: Windows) -> Starts:
    """The twin's state and inputs at the start of every window: the measured arm,
    gripper and objects, and the servos' past (the targets held during the periods
    before the start, or the setpoints tracking servos followed toward them) for
    actuators that keep a command history (a delay)."""
    w = windows
    data = mujoco.MjData(model)
    joints = [model.joint(j) for j in layout.arm_joints]
    arm_qpos, arm_dof = [j.qposadr[0] for j in joints], [j.dofadr[0] for j in joints]
    arm_act = [model.actuator(a).id for a in layout.arm_actuators]
    states = np.empty((len(w), mujoco.mj_stateSize(model, STATE)))
    inputs = np.empty((len(w), mujoco.mj_stateSize(model, INPUTS)))
    control_dt = 1.0 / w.fps
    lead = servo_lead(model)
    if lead is not None:  # tracking servos: their past is the setpoints they tracked
        past = tracking_setpoints(
            w.history[:, 0],
            w.history[:, 1:],
            control_substeps(model, w.fps),
            control_dt,
            lead,
        )
    for i in range(len(w)):
        mujoco.mj_resetData(model, data)
        place_measured(model, data, layout, w.objects, w.objects0[i], w.opening0[i])
        data.qpos[arm_qpos] = w.q0[i]
        data.qvel[arm_dof] = w.qd0[i]
        data.ctrl[arm_act] = w.history[i, -1]
        for a, act in enumerate(arm_act):
            samples = int(model.actuator_history[act, 0])
            if samples:
                times = -model.opt.timestep * np.arange(samples, 0, -1)
                if lead is None:
                    period = np.clip(
                        np.floor(times / control_dt).astype(int) + w.history.shape[1],
                        0,
                        w.history.shape[1] - 1,
                    )
                    values = w.history[i, period, a][:, None].copy()
                else:
                    step = np.floor(times / model.opt.timestep + 0.5).astype(int)
                    step = np.clip(step + past.shape[1], 0, past.shape[1] - 1)
                    values = past[i, step, a][:, None].copy()
                mujoco.mj_initCtrlHistory(model, data, act, times[:, None].copy(), values)
        mujoco.mj_forward(model, data)
        mujoco.mj_getState(model, data, states[i], STATE)
        mujoco.mj_getState(model, data, inputs[i], INPUTS)
    return Starts(states, inputs, previous=w.history[:, -1].copy())


def replay_signals(
    engine: WindowedReplay,
    models: Sequence[mujoco.MjModel],
    windows: Windows,
    starts: Starts,
) -> tuple[np.ndarray, np.ndarray]:
    """The compared signals each model predicts for every window, (len(models), n, W,
    n_signals), and the physics states at the compared rows, (len(models), n, W, size)."""
    w = windows
    ticks, held = engine.rollout(models, starts, w.targets, w.gripper)
    signals = np.empty((len(models), len(w), w.rows, len(w.names)))
    # The compared signals need no contact forces: skipping collision and the constraint
    # solver makes reading them back several times cheaper.
    skipped = mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    for m, model in enumerate(models):
        flags = model.opt.disableflags
        model.opt.disableflags = flags | skipped
        try:
            signals[m] = _read_signals(engine, model, w, ticks[m], held[m])
        finally:
            model.opt.disableflags = flags
    return signals, ticks


def _read_signals(
    engine: WindowedReplay,
    model: mujoco.MjModel,
    windows: Windows,
    ticks: np.ndarray,
    held: np.ndarray,
) -> np.ndarray:
    """The compared signals of one model at every compared row, (n, W, n_signals)."""
    w = windows
    data = mujoco.MjData(model)
    joints = [model.joint(j) for j in engine.layout.arm_joints]
    arm_qpos, arm_dof = [j.qposadr[0] for j in joints], [j.dofadr[0] for j in joints]
    tcp = model.site(engine.layout.tcp_site).id
    tau = "tau" in w.families
    offset = torque_offset(model, len(arm_dof))
    bodies = [
        model.body(n.removesuffix(".x")).id
        for n, family in zip(w.names, w.families, strict=True)
        if family == "object" and n.endswith(".x")
    ]
    signals = np.empty((len(w), w.rows, len(w.names)))
    for i in range(len(w)):
        for r in range(w.rows):
            engine.restore(model, data, ticks[i, r], held[i, r])
            row = [data.qpos[arm_qpos], data.qvel[arm_dof], data.site_xpos[tcp]]
            if tau:
                row.append(data.qfrc_actuator[arm_dof] + offset)
            row.extend(data.xpos[b] for b in bodies)
            signals[i, r] = np.concatenate(row)
    return signals
