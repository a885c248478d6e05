"""Fit a candidate effect's parameters to measured episodes with ``mujoco.sysid``.

The measured episodes are cut into shooting windows (:mod:`twinrl_sim.gap.windows`):
every window restarts the twin from what was measured at its first row, re-sends the
logged commands and is compared with the measurement at every later row. All windows
of all parameter points of a finite-difference Jacobian run as one batched call of the
twin's replay engine (:mod:`twinrl_sim.windowed`), the same replay localisation uses.

The fit itself is ``mujoco.sysid``'s: one :class:`sysid.Parameter` per effect, whose
modifier applies the effect to a copy of the twin's ``MjSpec``;
:func:`sysid.build_residual_fn` with this module's batched rollout and residual hooks;
:func:`sysid.optimize` (MuJoCo's bounded Levenberg-Marquardt);
:func:`sysid.calculate_intervals` for 95 % intervals.

Residuals are divided by each signal's sensor noise (:class:`NoiseFloor`), so that a
joint angle (rad), a torque (N m) and a position (m) weigh alike; the fit minimises
their sum of squares. The diagnosis scores a fit by a Gaussian likelihood whose
variance is fitted per signal (:func:`likelihood_term`), which the squares' minimum can
leave worse than the start: a large drop in one signal traded for a rise in another that
fitted well (a payload fitted to torques that a load cannot explain). Such a fit is
done again on that likelihood's bound at the start: each signal's squares weighed by
the inverse of its mean square there (:func:`signal_weights`). The logarithm is
concave, so the weighed sum bounds the likelihood from above and touches it at the
start: every step that lowers the sum lowers the likelihood, and the refit cannot end
worse than it started (:attr:`WindowReplay.refit_by_likelihood` says it was needed).
Every fit is not done so, because weights kept from a start whose torques were far off
leave those torques under-weighed once they fit (a hidden object mass of 4x fitted as
3.2x, the squares' fit 3.8x). A fit that still ends worse (a component reset to "no
effect") says so (:attr:`WindowReplay.ended_worse`) and the diagnosis reports it as
failed.
"""

from __future__ import annotations

import io
import logging
import math
from collections.abc import Sequence

import mujoco
import numpy as np
import scipy.optimize as scipy_optimize
from absl import logging as absl_logging
from mujoco import minimize, sysid
from mujoco.rollout import Rollout

from twinrl_sim.build import build_mjspec
from twinrl_sim.effects import apply_effects
from twinrl_sim.gap.candidates import CANDIDATES, Candidate, Fitted
from twinrl_sim.gap.gravity import GRAVITY_EFFECTS, separable_parts
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.gap.windows import DELAY_HISTORY, Windows, measured_starts, replay_signals
from twinrl_sim.spec import SceneSpec
from twinrl_sim.windowed import WindowedReplay

FD_STEP = 1e-3  # finite-difference step in optimiser units (see Candidate.scale)
MAX_ITERS = 12  # Levenberg-Marquardt iterations per fit; these fits converge in 3-8
XTOL = 1e-4  # relative step below which a fit has converged (far below any interval)
BIC_STEP = 0.5  # a fit whose last step changed its BIC by less than this has converged
# Shares of a screen's Gauss-Newton step tried (:meth:`WindowReplay.first_step`): from a
# payload of 0.1 kg the step puts its centre of gravity metres away (the torque is mass
# times centre, linearised at a near-zero mass), while a quarter of it explains much of
# a 2 kg tool; a half alone left it ranked below effects it is larger than.
STEP_FRACTIONS = (1.0, 0.5, 0.25)


def least_squares(
    params: sysid.ParameterDict, residual_fn, *, eps: float, xtol: float, max_iters: int
):
    """``sysid.optimize`` with MuJoCo's bounded Levenberg-Marquardt as the gap fits use
    it: (fitted parameters, the optimiser's result, iterations taken).

    Besides the optimiser's own step tolerance, a fit stops once its last step changed
    its BIC by less than :data:`BIC_STEP` (the step's share of the squared residuals
    times their count): what the diagnosis compares could then barely move, while a
    parameter whose value is near zero (an offset the arm does not have) would take
    steps relative to that value until ``max_iters``."""
    logging.getLogger("absl").setLevel(logging.ERROR)
    try:
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
            iter_callback=_stop_when_flat,
        )
    except _Flat as flat:
        return _flat_result(params, residual_fn, flat, eps)
    return fitted, result, len(result.extras.get("objective", [])) or max_iters


class _Flat(Exception):
    """Raised from the optimiser's iteration callback: the fit has converged at ``x``."""

    def __init__(self, x: np.ndarray, iterations: int) -> None:
        self.x, self.iterations = x, iterations


def _stop_when_flat(trace: list[minimize.IterLog]) -> None:
    last = trace[-1]
    if last.step is None or last.residual is None or not last.reduction > 0:
        return  # the final entry, or a step that did not help
    if last.residual.size * last.reduction < BIC_STEP * last.objective:
        raise _Flat(last.candidate + last.step, len(trace))


def _flat_result(params: sysid.ParameterDict, residual_fn, flat: _Flat, eps: float):
    """What :func:`sysid.optimize` returns, for a fit stopped at ``flat.x``: the
    parameters there and the Jacobian there (as the optimiser ends with)."""
    bounds = [bound[:, None] for bound in params.get_bounds()]  # columns, as x is
    x = np.clip(flat.x, *bounds)

    def residual(z: np.ndarray) -> np.ndarray:
        return np.concatenate(residual_fn(z, params)[0])

    jac, _ = minimize.jacobian_fd(residual, x, residual(x), eps, 0, bounds)
    fitted = params.copy()
    fitted.update_from_vector(x[:, 0])
    return fitted, scipy_optimize.OptimizeResult(x=x[:, 0], jac=jac), flat.iterations


def _remembering_last_point(residual_fn):
    """``residual_fn`` that answers the point it last evaluated alone from memory: the
    optimiser's last accepted point is asked for again, for the intervals and the
    information criteria, and each such replay of every window costs a rollout."""
    last: dict[bytes, tuple] = {}

    def residual(x, params, **kwargs):
        x = np.asarray(x, float)
        if (x.ndim > 1 and x.shape[1] != 1) or kwargs:  # finite differences' batch, options
            return residual_fn(x, params, **kwargs)
        key = x.ravel().tobytes()
        if key not in last:
            last.clear()
            last[key] = residual_fn(x, params)
        residuals, *rest = last[key]
        shape = (-1,) if x.ndim == 1 else (-1, 1)  # as asked: one point flat or as a column
        return ([r.reshape(shape) for r in residuals], *rest)

    return residual


def likelihood_term(residuals: np.ndarray) -> float:
    """-2 log-likelihood (up to a constant) of residuals (n, W, n_signals) under a
    Gaussian whose variance is fitted per signal: what the diagnosis's BIC scores."""
    rows = residuals.shape[0] * residuals.shape[1]
    rss = np.maximum(np.sum(residuals**2, axis=(0, 1)), 1e-300)
    return float(np.sum(rows * np.log(rss / rows)))


def signal_weights(residuals: np.ndarray) -> np.ndarray:
    """Per-signal weights (n_signals,) of residuals (n, W, n_signals) under which their
    weighed sum of squares is the bound of :func:`likelihood_term` that touches it here:
    one over each signal's root mean square."""
    mean_square = np.mean(residuals**2, axis=(0, 1))
    return 1.0 / np.sqrt(np.maximum(mean_square, 1e-12))


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
        self.ended_worse = False  # the last fit ended with a worse likelihood than it started
        # the last fit's squares ended worse by the likelihood, so it minimised the bound
        self.refit_by_likelihood = False
        self.gravity = (
            separable_parts(self.spec, self.spec.compile(), self.layout)
            if any(c.effect in GRAVITY_EFFECTS for c in self.free)
            else None
        )
        self.params = sysid.ParameterDict()
        for candidate in self.free:
            self.params.add(self._parameter(candidate, (start or {}).get(candidate.effect)))
        self.params.move_off_bounds()
        structure = self.edited_spec(self.params)
        model = structure.compile()
        self.engine = WindowedReplay(self.layout, windows.fps, pool)
        self.starts = measured_starts(model, self.layout, windows)
        self.sequences = self._sequences(structure, model)
        self.residual_fn = _remembering_last_point(
            sysid.build_residual_fn(
                models_sequences=[self.sequences],
                build_model=lambda params, _spec: self.edited_spec(params).compile(),
                custom_rollout=self._rollout,
                modify_residual=self._residual,
                n_threads=2,
            )
        )

    # ------------------------------------------------------------------ model
    def _parameter(self, candidate: Candidate, start: dict | None) -> sysid.Parameter:
        """The effect's parameters in optimiser units, one vector, starting at ``start``
        (its effects-file form) or at the candidate's default start."""
        nominal, low, high = [], [], []
        for field in candidate.fitted:
            size = self._size(field)
            lo, hi = field.bounds()
            if field.effect == "actuator_delay":
                hi = min(hi, DELAY_HISTORY)
            given = (start or {}).get(field.param)
            value = np.asarray(self._resolve(field.start) if given is None else given, float)
            if given is not None and self._components(field) is not None:
                value = value[list(self._components(field))]
            nominal.append(np.broadcast_to(value / field.scale, (size,)))
            low.append(np.full(size, lo / field.scale))
            high.append(np.full(size, hi / field.scale))
        return sysid.Parameter(
            candidate.effect,
            nominal=np.concatenate(nominal),
            min_value=np.concatenate(low),
            max_value=np.concatenate(high),
            modifier=lambda spec, p, c=candidate: self._apply(spec, c, p.value),
        )

    def _components(self, field: Fitted) -> tuple[int, ...] | None:
        """The per-joint components of ``field`` that are fitted (None: all of them):
        of the gravity model, those the joint torques can tell apart."""
        if self.gravity is None or not field.per_joint:
            return None
        return self.gravity.components(field.effect)

    def _size(self, field: Fitted) -> int:
        if field.per_joint:
            components = self._components(field)
            return len(self.layout.arm_joints) if components is None else len(components)
        return 3 if field.vector else 1

    def _expand(
        self, field: Fitted, values: np.ndarray, rest: float | tuple[float, ...]
    ) -> np.ndarray:
        """A field's fitted components as its full per-joint vector, ``rest`` (a number:
        only per-joint fields are fitted in part) elsewhere."""
        components = self._components(field)
        if components is None:
            return values
        full = np.full(len(self.layout.arm_joints), rest)
        full[list(components)] = values
        return full

    def _parts(self, candidate: Candidate, offset: int = 0):
        """(field, slice of the candidate's vector, from ``offset``) of each parameter."""
        for field in candidate.fitted:
            yield field, slice(offset, offset + self._size(field))
            offset += self._size(field)

    def _slices(self):
        """(candidate, slice of the parameter vector) of every free effect, in order."""
        offset = 0
        for candidate in self.free:
            size = sum(self._size(f) for f in candidate.fitted)
            yield candidate, slice(offset, offset + size)
            offset += size

    def _resolve(self, value: float | tuple[float, ...] | None) -> float | tuple[float, ...]:
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

    def physical(self, candidate: Candidate, value: np.ndarray) -> dict[str, float | list[float]]:
        """The candidate's parameters at ``value`` (optimiser units), effects-file form."""
        params = {}
        for field, part in self._parts(candidate):
            values = np.clip(np.asarray(value[part], float) * field.scale, *field.bounds())
            values = self._expand(field, values, self._resolve(field.null))
            params[field.param] = [float(v) for v in values] if field.vector else float(values[0])
        return params

    def interval(
        self, candidate: Candidate, half_width: np.ndarray
    ) -> dict[str, float | list[float]]:
        """Interval half-widths in the effect's units (``inf``: not identifiable)."""
        params = {}
        for field, part in self._parts(candidate):
            values = self._expand(field, np.asarray(half_width[part], float) * field.scale, np.inf)
            params[field.param] = [float(v) for v in values] if field.vector else float(values[0])
        return params

    def _apply(self, spec: mujoco.MjSpec, candidate: Candidate, value: np.ndarray) -> None:
        physical = self.physical(candidate, value)
        if candidate.effect == "actuator_delay":
            seconds = float(physical["seconds"])
            # A fixed-length history buffer and linear interpolation keep the state
            # size constant and the delay differentiable while it is being fitted.
            nsample = math.ceil(DELAY_HISTORY / spec.option.timestep) + 2
            for name in self.layout.arm_actuators:
                act = spec.actuator(name)
                act.delay, act.nsample, act.interp = seconds, nsample, 1
            return
        apply_effects(spec, self.layout, {candidate.effect: physical})

    def edited_spec(self, params: sysid.ParameterDict) -> mujoco.MjSpec:
        """A fresh copy of the twin's spec with the fixed effects and the parameters'
        (the parameters' modifiers edit a copy: effects add to nominal values)."""
        edited = self.spec.copy()
        if self.fixed:
            apply_effects(edited, self.layout, self.fixed)
        return sysid.apply_param_modifiers_spec(params, edited)

    # ------------------------------------------------------------- windows
    def _sequences(self, structure: mujoco.MjSpec, model: mujoco.MjModel) -> sysid.ModelSequences:
        w = self.windows
        rows = len(w) * w.measured.shape[1]
        times = np.arange(1, rows + 1) / w.fps  # one clock through all windows
        measured = sysid.TimeSeries.from_custom_map(
            times,
            w.measured.reshape(rows, -1),
            [(n, 1, sysid.SignalType.CustomObs) for n in w.names],
        )
        held = self.engine.period_inputs(model, self.starts, w.targets, w.gripper)
        ctrl = held[:, :, : model.nu].reshape(rows, -1)
        control = sysid.TimeSeries.from_control_names(np.arange(rows) / w.fps, ctrl, model)
        absl_logging.set_verbosity(absl_logging.ERROR)  # "sensor dimension" warnings
        return sysid.ModelSequences(
            "twin",
            structure,
            "windows",
            self.starts.state[0],
            control,
            measured,
            allow_missing_sensors=True,
        )

    # ------------------------------------------------------------ rollout
    def predict(self, models: Sequence[mujoco.MjModel]) -> tuple[np.ndarray, np.ndarray]:
        """Signals predicted by each model for every window: (len(models), n, W, n_sig),
        and the physics states at the compared rows (len(models), n, W, size)."""
        return replay_signals(self.engine, models, self.windows, self.starts)

    def _rollout(self, models, control_signal, initial_states, param_dicts, **_):
        """``custom_rollout`` hook: every window of every parameter point in one batch."""
        signals, ticks = self.predict(models)
        rows = signals.shape[1] * signals.shape[2]
        times = self.sequences.sensordata[0].times
        out = []
        for m, model in enumerate(models):
            state = ticks[m].reshape(rows, -1).copy()
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
        at_start = self.residuals()
        before = likelihood_term(at_start)
        objective = self.residual_fn
        params, result, iterations = least_squares(
            self.params.copy(), objective, eps=FD_STEP, xtol=XTOL, max_iters=max_iters
        )
        self.refit_by_likelihood = likelihood_term(self.residuals(params.as_vector())) > before
        if self.refit_by_likelihood:
            # The squares' minimum is worse by the likelihood than the start: minimise the
            # likelihood's bound at the start instead, which cannot end worse.
            objective = self._weighed(signal_weights(at_start))
            params, result, more = least_squares(
                self.params.copy(), objective, eps=FD_STEP, xtol=XTOL, max_iters=max_iters
            )
            iterations += more
        x = params.as_vector()
        if not np.any(result.jac):  # the data say nothing about these parameters
            half_width = np.full(len(x), np.inf)
        else:
            res, _, _ = objective(x, params.copy())
            _, half_width = sysid.calculate_intervals(res, result.jac)
        # A component the data cannot pin down (e.g. the offset of a wrist turning about
        # the TCP axis) wanders freely; report it at "no effect", interval unbounded.
        low, high = self.params.get_bounds()
        loose = ~(np.asarray(half_width) < (high - low) / 2)
        x = np.where(loose, self._null_vector(), x)
        self.ended_worse = likelihood_term(self.residuals(x)) > before + 1e-6
        return x, np.where(loose, np.inf, half_width), iterations

    def first_step(self) -> tuple[np.ndarray, np.ndarray]:
        """One Gauss-Newton step from the start, as a screen of what a fit could reach:
        (the best of the start and the step's :data:`STEP_FRACTIONS`, in optimiser units;
        the residuals there, shaped as :meth:`residuals`). Costs the Jacobian's rollouts
        and one more batch, a single iteration of :meth:`fit`."""
        shape = self.windows.measured.shape
        start = self.params.as_vector()[:, None]
        bounds = [bound[:, None] for bound in self.params.get_bounds()]

        def residual(z: np.ndarray) -> np.ndarray:
            return np.concatenate(self.residual_fn(z, self.params.copy())[0])

        at_start = residual(start)
        jac, _ = minimize.jacobian_fd(residual, start, at_start, FD_STEP, 0, bounds)
        norms = np.linalg.norm(jac, axis=0)
        norms[norms == 0] = 1.0  # a parameter the data do not see: no step
        step = np.linalg.lstsq(jac / norms, -at_start[:, 0], rcond=None)[0] / norms
        trials = np.clip(start + step[:, None] * np.array([STEP_FRACTIONS]), *bounds)
        points = np.column_stack([start, trials])
        residuals = np.column_stack([at_start, residual(trials)])
        scores = [likelihood_term(residuals[:, i].reshape(shape)) for i in range(points.shape[1])]
        best = int(np.argmin(scores))
        return points[:, best], residuals[:, best].reshape(shape)

    def _weighed(self, weights: np.ndarray):
        """:attr:`residual_fn` with each signal's residuals times its weight."""
        signals = len(weights)

        def residual(x, params, **kwargs):
            residuals, *rest = self.residual_fn(x, params, **kwargs)
            weighed = []
            for r in residuals:
                w = np.tile(weights, len(r) // signals)
                weighed.append(r * (w[:, None] if r.ndim == 2 else w))
            return (weighed, *rest)

        return residual

    def _null_vector(self) -> np.ndarray:
        """The free parameters' "no effect" values, in optimiser units."""
        null = np.empty(self.params.size)
        for candidate, part in self._slices():
            for field, own in self._parts(candidate, part.start):
                null[own] = np.asarray(self._resolve(field.null), float) / field.scale
        return null

    def effects_at(self, x: np.ndarray) -> dict[str, dict]:
        """The fixed effects plus the free ones at ``x``, in effects-file form."""
        effects = dict(self.fixed)
        for candidate, part in self._slices():
            effects[candidate.effect] = self.physical(candidate, x[part])
        return effects

    def intervals_at(self, half_width: np.ndarray) -> dict[str, dict]:
        """Interval half-widths of the free effects, in effects-file form."""
        return {c.effect: self.interval(c, half_width[part]) for c, part in self._slices()}
