"""Fit a candidate effect's parameters to measured episodes with ``mujoco.sysid``.

The measured episodes are cut into shooting windows (``window`` control steps each).
Every window restarts the twin from what was measured at its first row (arm joints and
velocities, gripper opening, object poses; a resting object's position is the mean
over its rest, since a tracker's millimetre of noise would otherwise start it inside
the table or the fingers), re-sends the logged joint targets and
gripper commands at the physics rate (held for a control period, as the robot holds
them) and is compared with the measurement at every later row. All windows of all
parameter points of a finite-difference Jacobian run as one batched
``mujoco.rollout`` call.

The fit itself is ``mujoco.sysid``'s: one :class:`sysid.Parameter` per effect, whose
modifier applies the effect to a copy of the twin's ``MjSpec``;
:func:`sysid.build_residual_fn` with this module's batched rollout and residual hooks;
:func:`sysid.optimize` (MuJoCo's bounded Levenberg-Marquardt);
:func:`sysid.calculate_intervals` for 95 % intervals.

Residuals are divided by each signal's sensor noise (:class:`NoiseFloor`), so that a
joint angle (rad), a torque (N m) and a position (m) weigh alike.
"""

from __future__ import annotations

import io
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import mujoco
import numpy as np
from absl import logging as absl_logging
from mujoco import sysid
from mujoco.rollout import Rollout

from twinrl_data import schema as contract
from twinrl_sim.build import build_mjspec
from twinrl_sim.effects import apply_effects
from twinrl_sim.errors import TwinError
from twinrl_sim.gap.candidates import CANDIDATES, Candidate
from twinrl_sim.layout import CellLayout
from twinrl_sim.robots import gripper as gripper_lib
from twinrl_sim.spec import SceneSpec

FD_STEP = 1e-3  # finite-difference step in optimiser units (see Candidate.scale)
MAX_ITERS = 12  # Levenberg-Marquardt iterations per fit; these fits converge in 3-8
XTOL = 1e-4  # relative step below which a fit has converged (far below any interval)


@dataclass(frozen=True)
class NoiseFloor:
    """Standard deviation of each measured signal family: the residuals' unit.

    The defaults are those of a UR e-series arm's joint encoders, velocity estimate,
    TCP pose and joint torque estimate, of a tracked object's position, and of a
    camera image compared in standardised grey levels and in colour.
    """

    q: float = 2e-4  # rad
    qd: float = 2e-3  # rad/s
    tcp: float = 3e-4  # m
    tau: float = 0.05  # N m
    object: float = 1e-3  # m
    image: float = 0.05  # standardised grey level of a compared image (see gap.camera)
    colour: float = 0.02  # colour level (0-1) of a box-averaged image (see gap.appearance)

    @classmethod
    def parse(cls, text: str) -> NoiseFloor:
        """``q=2e-4,tau=0.1`` -> a NoiseFloor with those entries changed."""
        known = {f.name for f in fields(cls)}
        values = {}
        for item in filter(None, (p.strip() for p in text.split(","))):
            key, _, value = item.partition("=")
            if key not in known:
                raise TwinError(
                    f"--noise: unknown signal family '{key}'; use {', '.join(sorted(known))}"
                )
            try:
                values[key] = float(value)
            except ValueError:
                raise TwinError(f"--noise: '{item}' needs a number, e.g. {key}=1e-3") from None
            if not values[key] > 0:
                raise TwinError(f"--noise: {key} must be positive, got {value}")
        return cls(**values)


DELAY_HISTORY = 0.3  # s: the longest actuator delay a fit can reach
# What a window's rollout sets at every step: the servo and gripper commands, and the
# poses of mocap bodies (targets and fixtures; they are inputs, not physics state).
INPUTS = int(
    mujoco.mjtState.mjSTATE_CTRL
    | mujoco.mjtState.mjSTATE_MOCAP_POS
    | mujoco.mjtState.mjSTATE_MOCAP_QUAT
)


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
    window: int = 20,
    control_hz: float,
) -> Windows:
    """Cut every episode into consecutive windows of ``window`` compared rows.

    A tail shorter than a window is left out. Signals are those every episode has:
    joint angles and velocities and the TCP position always; joint torques when all
    episodes log ``observation.effort``; object positions when all log them.
    """
    if window < 2:
        raise TwinError(f"--window must be at least 2 steps, got {window}")
    arm = layout.arm_joints
    for episode in episodes:
        _check_episode(episode, arm, control_hz)
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
        # Before the first row the robot held where it stood.
        padded = np.vstack([np.repeat(q[:1], history_steps, axis=0), targets])
        for start in range(0, len(state) - window, window):
            parts["measured"].append(measured[start + 1 : start + window + 1])
            parts["q0"].append(q[start])
            parts["qd0"].append(qd[start])
            parts["opening0"].append(opening[start])
            parts["objects0"].append(start_poses[start])
            parts["targets"].append(targets[start : start + window])
            parts["gripper"].append(gripper[start : start + window])
            parts["history"].append(padded[start : start + history_steps])
            parts["episode"].append(e_index)
            parts["start"].append(start)
    if not parts["q0"]:
        raise TwinError(
            f"no episode is longer than one window ({window} steps); record longer "
            "episodes or pass a smaller --window"
        )
    arrays = {k: np.asarray(v) for k, v in parts.items()}
    objects_logged = list(objects) if with_objects else []
    return Windows(names, families, objects_logged, **arrays, fps=control_hz)


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


def _check_episode(episode: contract.Episode, arm: Sequence[str], control_hz: float) -> None:
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
    if abs(episode.meta.fps - control_hz) > 1e-6 * control_hz:
        raise TwinError(
            f"episode {ident} is at {episode.meta.fps:g} Hz but the twin's control runs at "
            f"{control_hz:g} Hz; import it with --fps {control_hz:g}"
        )


def least_squares(
    params: sysid.ParameterDict, residual_fn, *, eps: float, xtol: float, max_iters: int
):
    """``sysid.optimize`` with MuJoCo's bounded Levenberg-Marquardt as the gap fits use
    it: (fitted parameters, the optimiser's result, iterations taken)."""
    logging.getLogger("absl").setLevel(logging.ERROR)
    fitted, result = sysid.optimize(
        params,
        residual_fn,
        optimizer="mujoco",
        verbose=False,
        max_iters=max_iters,
        eps=eps,
        x_scale="jac",  # column-normalised: the damping is then of order one
        mu_factor=10**0.5,  # few rejected trial steps (each costs a rollout)
        xtol=xtol,
        output=io.StringIO(),  # the backend prints every iteration; keep it quiet
    )
    return fitted, result, len(result.extras.get("objective", [])) or max_iters


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
        data.qpos[fingers] = np.clip(gripper_lib.STROKE - opening / 2, 0, gripper_lib.STROKE)


class WindowReplay:
    """The twin of ``scene`` (plus ``fixed`` effects) replaying ``windows``, with the
    effects of ``free`` adjustable: a ``mujoco.sysid`` residual over all windows."""

    def __init__(
        self,
        scene: SceneSpec,
        windows: Windows,
        noise: NoiseFloor,
        *,
        fixed: dict[str, dict] | None = None,
        free: Sequence[str] = (),
        start: dict[str, dict] | None = None,
        pool: Rollout | None = None,
    ) -> None:
        self.windows = windows
        self.fixed = dict(fixed or {})
        self.free = [CANDIDATES[name] for name in free]
        self.spec, self.layout = build_mjspec(scene)
        self.scale = np.array([getattr(noise, f) for f in windows.families])
        self.pool = pool or Rollout(nthread=2)
        self.params = sysid.ParameterDict()
        for candidate in self.free:
            self.params.add(self._parameter(candidate, (start or {}).get(candidate.effect)))
        self.params.move_off_bounds()
        structure = self.edited_spec(self.params)
        model = structure.compile()
        self.substeps = round(1.0 / (windows.fps * model.opt.timestep))
        self.initial_states, self.initial_inputs = self._initial_states(model)
        self.sequences = self._sequences(structure, model)
        self.residual_fn = sysid.build_residual_fn(
            models_sequences=[self.sequences],
            build_model=lambda params, _spec: self.edited_spec(params).compile(),
            custom_rollout=self._rollout,
            modify_residual=self._residual,
            n_threads=2,
        )

    # ------------------------------------------------------------------ model
    def _parameter(self, candidate: Candidate, start: dict | None) -> sysid.Parameter:
        """The effect's parameter in optimiser units, starting at ``start`` (its
        effects-file form) or at the candidate's default start."""
        low, high = candidate.bounds()
        size = self._size(candidate)
        if candidate.effect == "actuator_delay":
            high = min(high, DELAY_HISTORY)
        if start is not None:
            value = np.asarray(start[candidate.param], float)
        else:
            value = np.array(self._resolve(candidate.start))
        return sysid.Parameter(
            candidate.effect,
            nominal=np.broadcast_to(value / candidate.scale, (size,)).copy(),
            min_value=np.full(size, low / candidate.scale),
            max_value=np.full(size, high / candidate.scale),
            modifier=lambda spec, p, c=candidate: self._apply(spec, c, p.value),
        )

    def _size(self, candidate: Candidate) -> int:
        return len(self.layout.arm_joints) if candidate.per_joint else 1

    def _slices(self):
        """(candidate, slice of the parameter vector) of every free effect, in order."""
        offset = 0
        for candidate in self.free:
            yield candidate, slice(offset, offset + self._size(candidate))
            offset += self._size(candidate)

    def _resolve(self, value: float | None) -> float:
        """A candidate's start or null value; ``None``: the object's nominal friction
        (the only candidate whose neutral value is the scene's own)."""
        return self._nominal_friction() if value is None else value

    def _nominal_friction(self) -> float:
        geoms = [
            g
            for name in self.layout.manipulated
            for g in self.spec.body(name).geoms
            if g.contype or g.conaffinity
        ]
        return float(geoms[0].friction[0]) if geoms else 1.0

    def physical(self, candidate: Candidate, value: np.ndarray) -> float | list[float]:
        values = np.clip(np.asarray(value, float) * candidate.scale, *candidate.bounds())
        return [float(v) for v in values] if candidate.per_joint else float(values[0])

    def interval(self, candidate: Candidate, half_width: np.ndarray) -> float | list[float]:
        """Interval half-widths in the effect's units (``inf``: not identifiable)."""
        values = np.asarray(half_width, float) * candidate.scale
        return [float(v) for v in values] if candidate.per_joint else float(values[0])

    def _apply(self, spec: mujoco.MjSpec, candidate: Candidate, value: np.ndarray) -> None:
        physical = self.physical(candidate, value)
        if candidate.effect == "actuator_delay":
            # A fixed-length history buffer and linear interpolation keep the state
            # size constant and the delay differentiable while it is being fitted.
            nsample = math.ceil(DELAY_HISTORY / spec.option.timestep) + 2
            for name in self.layout.arm_actuators:
                act = spec.actuator(name)
                act.delay, act.nsample, act.interp = float(physical), nsample, 1
            return
        apply_effects(spec, self.layout, {candidate.effect: {candidate.param: physical}})

    def edited_spec(self, params: sysid.ParameterDict) -> mujoco.MjSpec:
        """A fresh copy of the twin's spec with the fixed effects and the parameters'
        (the parameters' modifiers edit a copy: effects add to nominal values)."""
        edited = self.spec.copy()
        if self.fixed:
            apply_effects(edited, self.layout, self.fixed)
        return sysid.apply_param_modifiers_spec(params, edited)

    # ------------------------------------------------------------- windows
    def _initial_states(self, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
        """Physics state (mjSTATE_FULLPHYSICS) and inputs (:data:`INPUTS`) at the start
        of every window."""
        w = self.windows
        data = mujoco.MjData(model)
        arm_qpos, arm_dof = self._arm_addresses(model)
        arm_act = [model.actuator(a).id for a in self.layout.arm_actuators]
        size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        states = np.empty((len(w), size))
        inputs = np.empty((len(w), mujoco.mj_stateSize(model, INPUTS)))
        control_dt = 1.0 / w.fps
        for i in range(len(w)):
            mujoco.mj_resetData(model, data)
            place_measured(model, data, self.layout, w.objects, w.objects0[i], w.opening0[i])
            data.qpos[arm_qpos] = w.q0[i]
            data.qvel[arm_dof] = w.qd0[i]
            data.ctrl[arm_act] = w.history[i, -1]
            for a, act in enumerate(arm_act):
                samples = int(model.actuator_history[act, 0])
                if samples:
                    # The servo's past: the targets held during the previous periods.
                    times = -model.opt.timestep * np.arange(samples, 0, -1)
                    period = np.clip(
                        np.floor(times / control_dt).astype(int) + w.history.shape[1],
                        0,
                        w.history.shape[1] - 1,
                    )
                    values = w.history[i, period, a][:, None].copy()
                    mujoco.mj_initCtrlHistory(model, data, act, times[:, None].copy(), values)
            mujoco.mj_forward(model, data)
            mujoco.mj_getState(model, data, states[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
            mujoco.mj_getState(model, data, inputs[i], INPUTS)
        return states, inputs

    def _arm_addresses(self, model: mujoco.MjModel) -> tuple[list[int], list[int]]:
        """qpos and dof addresses of the arm joints."""
        joints = [model.joint(j) for j in self.layout.arm_joints]
        return [j.qposadr[0] for j in joints], [j.dofadr[0] for j in joints]

    def _controls(self, model: mujoco.MjModel) -> np.ndarray:
        """(n, W * substeps, :data:`INPUTS` size): each target held for its control
        period, mocap bodies where they were at the window's start. ``ctrl`` comes
        first in the inputs (mjtState order)."""
        w = self.windows
        inputs = np.repeat(self.initial_inputs[:, None], w.targets.shape[1], axis=1)
        inputs[:, :, [model.actuator(a).id for a in self.layout.arm_actuators]] = w.targets
        if self.layout.gripper_actuator:
            inputs[:, :, model.actuator(self.layout.gripper_actuator).id] = w.gripper
        return np.repeat(inputs, self.substeps, axis=1)

    def _sequences(self, structure: mujoco.MjSpec, model: mujoco.MjModel) -> sysid.ModelSequences:
        w = self.windows
        rows = len(w) * w.measured.shape[1]
        times = np.arange(1, rows + 1) / w.fps  # one clock through all windows
        measured = sysid.TimeSeries.from_custom_map(
            times,
            w.measured.reshape(rows, -1),
            [(n, 1, sysid.SignalType.CustomObs) for n in w.names],
        )
        ctrl = self._controls(model)[:, :: self.substeps, : model.nu].reshape(rows, -1)
        control = sysid.TimeSeries.from_control_names(np.arange(rows) / w.fps, ctrl, model)
        absl_logging.set_verbosity(absl_logging.ERROR)  # "sensor dimension" warnings
        return sysid.ModelSequences(
            "twin",
            structure,
            "windows",
            self.initial_states[0],
            control,
            measured,
            allow_missing_sensors=True,
        )

    # ------------------------------------------------------------ rollout
    def predict(self, models: Sequence[mujoco.MjModel]) -> tuple[np.ndarray, np.ndarray]:
        """Signals predicted by each model for every window: (len(models), n, W, n_sig),
        and the physics states at the compared rows."""
        w = self.windows
        n, rows = len(w), w.measured.shape[1]
        ctrl = self._controls(models[0])
        batch = [m for m in models for _ in range(n)]
        datas = [mujoco.MjData(models[0]) for _ in range(2)]
        state, _ = self.pool.rollout(
            batch,
            datas,
            np.tile(self.initial_states, (len(models), 1)),
            np.tile(ctrl, (len(models), 1, 1)),
            control_spec=INPUTS,
        )
        ticks = state[:, self.substeps - 1 :: self.substeps]  # (batch, W, nstate)
        signals = np.empty((len(models), n, rows, len(w.names)))
        for m, model in enumerate(models):
            signals[m] = self._signals(model, ticks[m * n : (m + 1) * n], ctrl)
        return signals, ticks

    def _signals(self, model: mujoco.MjModel, ticks: np.ndarray, ctrl: np.ndarray) -> np.ndarray:
        w = self.windows
        data = mujoco.MjData(model)
        arm_qpos, arm_dof = self._arm_addresses(model)
        tcp = model.site(self.layout.tcp_site).id
        tau = "tau" in w.families
        bodies = [
            model.body(n.removesuffix(".x")).id
            for n, family in zip(w.names, w.families, strict=True)
            if family == "object" and n.endswith(".x")
        ]
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        out = np.empty((len(w), ticks.shape[1], len(w.names)))
        for i in range(len(w)):
            for r in range(ticks.shape[1]):
                mujoco.mj_setState(model, data, ticks[i, r], spec)
                mujoco.mj_setState(model, data, ctrl[i, (r + 1) * self.substeps - 1], INPUTS)
                mujoco.mj_forward(model, data)
                row = [data.qpos[arm_qpos], data.qvel[arm_dof], data.site_xpos[tcp]]
                if tau:
                    row.append(data.qfrc_actuator[arm_dof])
                row.extend(data.xpos[b] for b in bodies)
                out[i, r] = np.concatenate(row)
        return out

    def _rollout(self, models, control_signal, initial_states, param_dicts, **_):
        """``custom_rollout`` hook: every window of every parameter point in one batch."""
        signals, ticks = self.predict(models)
        rows = signals.shape[1] * signals.shape[2]
        times = self.sequences.sensordata[0].times
        out = []
        for m, model in enumerate(models):
            state = ticks[m * len(self.windows) : (m + 1) * len(self.windows)]
            state = state.reshape(rows, -1).copy()
            state[:, 0] = times  # one clock through all windows
            out.append(
                sysid.SystemTrajectory(
                    model=model,
                    control=control_signal[m],
                    sensordata=sysid.TimeSeries(
                        times,
                        signals[m].reshape(rows, -1),
                        self.sequences.sensordata[0].signal_mapping,
                    ),
                    initial_state=initial_states[m],
                    state=sysid.TimeSeries(times, state),
                )
            )
        return out

    def _residual(self, params, predicted, measured, model, return_pred_all, state=None):
        """``modify_residual`` hook: measured minus predicted, in noise units."""
        return (measured.data - predicted.data) / self.scale, predicted, measured

    # ---------------------------------------------------------------- use
    def residuals(self, x: np.ndarray | None = None) -> np.ndarray:
        """Residuals (n, W, n_signals) in noise units at ``x`` (default: the start)."""
        x = self.params.as_vector() if x is None else x
        res, _, _ = self.residual_fn(np.asarray(x, float), self.params.copy())
        return np.concatenate(res).reshape(self.windows.measured.shape)

    def fit(self, max_iters: int = MAX_ITERS) -> tuple[np.ndarray, np.ndarray, int]:
        """Least-squares fit of the free effects: (x, 95 % half-widths, iterations), in
        optimiser units (see :meth:`physical`)."""
        if not self.free:
            return np.zeros(0), np.zeros(0), 0
        params, result, iterations = least_squares(
            self.params, self.residual_fn, eps=FD_STEP, xtol=XTOL, max_iters=max_iters
        )
        x = params.as_vector()
        if not np.any(result.jac):  # the data say nothing about these parameters
            half_width = np.full(len(x), np.inf)
        else:
            res, _, _ = self.residual_fn(x, params.copy())
            _, half_width = sysid.calculate_intervals(res, result.jac)
        # A component the data cannot pin down (e.g. the offset of a wrist turning about
        # the TCP axis) wanders freely; report it at "no effect", interval unbounded.
        low, high = self.params.get_bounds()
        loose = ~(np.asarray(half_width) < (high - low) / 2)
        x = np.where(loose, self._null_vector(), x)
        return x, np.where(loose, np.inf, half_width), iterations

    def _null_vector(self) -> np.ndarray:
        """The free parameters' "no effect" values, in optimiser units."""
        null = np.empty(self.params.size)
        for candidate, part in self._slices():
            null[part] = self._resolve(candidate.null) / candidate.scale
        return null

    def effects_at(self, x: np.ndarray) -> dict[str, dict]:
        """The fixed effects plus the free ones at ``x``, in effects-file form."""
        effects = dict(self.fixed)
        for candidate, part in self._slices():
            effects[candidate.effect] = {candidate.param: self.physical(candidate, x[part])}
        return effects

    def intervals_at(self, half_width: np.ndarray) -> dict[str, dict]:
        """Interval half-widths of the free effects, in effects-file form."""
        return {
            c.effect: {c.param: self.interval(c, half_width[part])} for c, part in self._slices()
        }
