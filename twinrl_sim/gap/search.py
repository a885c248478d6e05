"""The search through the motion candidates: each round screens every candidate, fits the
most promising, and judges them against the twin with the effects named so far.

A full fit of every candidate in every round is what made a diagnosis slow at a
controller's log rate: most candidates explain little, and a fit of one that explains
nothing still takes a few iterations to stop. So each candidate first takes one
Gauss-Newton step from its start (:meth:`~twinrl_sim.gap.identify.WindowReplay.first_step`,
the cost of one iteration), and only the :data:`SCREEN_KEEP` whose step explains most
(lowest BIC) are fitted in full. The others are reported at that step, marked
``screened``: their first steps explained less than those of the fitted ones, and on
the benchmark's logs a step ranks the candidates as their fits do (the hidden effects
among the fitted, every round). A candidate masked by a larger effect is screened again
in the next round, with that effect named.

Judging is the naming rule: a candidate is *significant* when its BIC beats the twin
without it by more than :data:`BIC_MARGIN` and it cuts the held-out error by at least
:data:`MIN_HELDOUT_GAIN`.

A round's screens, and then its fits, are independent of one another: given an
:class:`~twinrl_data.executor.Executor`, each is one of its jobs (worker processes, or
Ray tasks on a cluster), and the round comes out the same as in one process.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from mujoco.rollout import Rollout

from twinrl_data.executor import Executor
from twinrl_sim.gap.identify import WindowReplay, likelihood_term

BIC_MARGIN = 10.0  # BIC difference counted as very strong evidence (Kass & Raftery scale)
MIN_HELDOUT_GAIN = 0.05  # relative held-out error reduction a named effect must bring
JOINT_REFITS = 2  # best candidates refit with the named effects when none is significant
# Candidates fitted in full per round, those whose first step explains most; three leave
# room for an effect that starts slowly (a delay's first step reaches part of its fit).
SCREEN_KEEP = 3


@dataclass
class CandidateResult:
    """One candidate effect fitted (or screened) in one round."""

    effect: str
    params: dict[str, float | list[float]]
    ci: dict[str, float | list[float]]  # 95 % half-widths, same units as params
    heldout_error: float
    aic: float
    bic: float
    delta_bic: float  # against the twin without this candidate (negative: better)
    significant: bool
    iterations: int
    seconds: float
    compared: str = "motion"  # the residuals it was judged on: motion, or images:<camera>
    fit_failed: bool = False  # its fit ended worse than it started: never named
    # Its squares' fit ended worse by the likelihood than it started, so it was fitted on
    # the likelihood's bound (:meth:`~twinrl_sim.gap.identify.WindowReplay.fit`).
    by_likelihood: bool = False
    # Judged at its first Gauss-Newton step, not fitted: others' steps explained more
    # (module docstring); its intervals are not computed (inf).
    screened: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Score:
    """The twin with some effects, on the fitted and the held-out windows."""

    heldout_error: float
    aic: float
    bic: float


def information(residuals: np.ndarray, k: int) -> tuple[float, float]:
    """(AIC, BIC) of residuals (n, W, n_signals) with a Gaussian likelihood whose
    variance is fitted per signal (:func:`likelihood_term`), for ``k`` fitted parameters."""
    rows = residuals.shape[0] * residuals.shape[1]
    neg2_loglik = likelihood_term(residuals)
    return neg2_loglik + 2 * k, neg2_loglik + k * math.log(residuals.shape[2] * rows)


def rms(residuals: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residuals**2)))


def score(scene, fit_on, held, noise, fixed, rollout, parameters: int = 0) -> Score:
    """The twin with ``fixed`` effects (``parameters`` numbers fitted) as it stands."""
    train = WindowReplay(scene, fit_on, noise, fixed=fixed, pool=rollout).residuals()
    heldout = WindowReplay(scene, held, noise, fixed=fixed, pool=rollout).residuals()
    aic, bic = information(train, parameters)
    return Score(rms(heldout), aic, bic)


def size(effects: dict[str, dict]) -> int:
    """How many numbers ``effects`` hold (their fitted parameters)."""
    return sum(np.size(value) for params in effects.values() for value in params.values())


@dataclass(frozen=True)
class CandidateJob:
    """One candidate's screen or fit in a round, with all it is judged on: a job that
    runs anywhere (:func:`run_candidate`)."""

    kind: str  # screen, fit, or joint (refit together with the named effects)
    name: str
    scene: Any
    fit_on: Any
    held: Any
    noise: Any
    fixed: dict
    baseline: Score


def run_candidate(job: CandidateJob, rollout: Rollout) -> CandidateResult:
    """``job`` screened or fitted with ``rollout``'s threads."""
    args = (job.scene, job.fit_on, job.held, job.noise, job.fixed, job.name, job.baseline)
    if job.kind == "screen":
        return screen_candidate(*args, rollout)
    return fit_candidate(*args, rollout, jointly=job.kind == "joint")


_worker_rollout: Rollout | None = None  # a worker's own threads, made by its first job


def _run_in_worker(job: CandidateJob) -> CandidateResult:
    global _worker_rollout
    if _worker_rollout is None:
        _worker_rollout = Rollout(nthread=1)  # a worker is one CPU's job
    return run_candidate(job, _worker_rollout)


def _run_all(
    jobs: list[CandidateJob],
    rollout: Rollout,
    executor: Executor | None,
    log: Callable[[str], None],
) -> list[CandidateResult]:
    """Every job's result, in order: here one after another, or on ``executor``."""
    if executor is None:
        results = []
        for job in jobs:
            log(f"{'screening' if job.kind == 'screen' else 'fitting'} {job.name}")
            results.append(run_candidate(job, rollout))
        return results
    verb = "screening" if jobs[0].kind == "screen" else "fitting"
    log(f"{verb} {', '.join(j.name for j in jobs)} on {executor.workers} workers")
    return executor.map(_run_in_worker, jobs)


def search_round(
    scene,
    fit_on,
    held,
    noise,
    fixed,
    pool: list[str],
    baseline: Score,
    rollout,
    log,
    keep: int | None = SCREEN_KEEP,
    executor: Executor | None = None,
) -> list[CandidateResult]:
    """One round: every candidate of ``pool`` screened, the best ``keep`` fitted (None:
    every candidate fitted, unscreened), and, when none of them is significant with
    named effects held, the best :data:`JOINT_REFITS` refit together with those (held
    where they were named, the named effects keep what they absorbed of the next one: a
    friction fitted without the rotor inertia beside it takes part of its torque). Best
    first: fitted by held-out error, then the screened ones by BIC. The screens, then
    the fits, run on ``executor`` when one is given (here with ``rollout`` otherwise)."""

    def jobs(kind: str, names: list[str]) -> list[CandidateJob]:
        return [
            CandidateJob(kind, name, scene, fit_on, held, noise, fixed, baseline) for name in names
        ]

    screens, chosen = [], list(pool)
    if keep is not None and keep < len(pool):
        screens = _run_all(jobs("screen", pool), rollout, executor, log)
        screens.sort(key=lambda r: r.bic)
        chosen, screens = [r.effect for r in screens[:keep]], screens[keep:]
    fitted = _run_all(jobs("fit", chosen), rollout, executor, log) if chosen else []
    fitted.sort(key=lambda r: r.heldout_error)
    if fixed and fitted and not fitted[0].significant:
        again = [r.effect for r in fitted[:JOINT_REFITS]]
        joint = _run_all(jobs("joint", again), rollout, executor, log)
        fitted = sorted(joint + fitted[JOINT_REFITS:], key=lambda r: r.heldout_error)
    return fitted + screens


def _judged(
    scene, held, noise, rollout, replay: WindowReplay, x, residuals, k: int, baseline: Score
) -> tuple[dict, float, float, float, bool]:
    """(effects at ``x``, held-out error, AIC, BIC, passes the naming rule) of a
    candidate whose training residuals at ``x`` are ``residuals``, ``k`` numbers fitted."""
    aic, bic = information(residuals, k)
    effects = replay.effects_at(x)
    heldout = WindowReplay(scene, held, noise, fixed=effects, pool=rollout).residuals()
    error = rms(heldout)
    passes = bic < baseline.bic - BIC_MARGIN and error <= (1 - MIN_HELDOUT_GAIN) * (
        baseline.heldout_error
    )
    return effects, error, aic, bic, passes


def screen_candidate(
    scene, fit_on, held, noise, fixed, name, baseline: Score, rollout
) -> CandidateResult:
    """``name`` judged at its first Gauss-Newton step with the named effects held."""
    started = time.perf_counter()
    replay = WindowReplay(scene, fit_on, noise, fixed=fixed, free=[name], pool=rollout)
    x, residuals = replay.first_step()
    effects, error, aic, bic, passes = _judged(
        scene, held, noise, rollout, replay, x, residuals, len(x), baseline
    )
    return CandidateResult(
        effect=name,
        params=effects[name],
        ci=replay.intervals_at(np.full(len(x), np.inf))[name],
        heldout_error=error,
        aic=aic,
        bic=bic,
        delta_bic=bic - baseline.bic,
        significant=bool(passes),
        iterations=1,
        seconds=time.perf_counter() - started,
        screened=True,
    )


def fit_candidate(
    scene, fit_on, held, noise, fixed, name, baseline: Score, rollout, jointly: bool = False
) -> CandidateResult:
    """``name`` fitted with the named effects (``fixed``) held, or ``jointly`` refit with
    them (counted in the information criteria as the candidate's parameters only)."""
    started = time.perf_counter()
    if jointly:
        kept, refitting, start = {}, list(fixed), fixed
    else:
        kept, refitting, start = fixed, [], None
    replay = WindowReplay(
        scene, fit_on, noise, fixed=kept, free=[*refitting, name], start=start, pool=rollout
    )
    x, half_width, iterations = replay.fit()
    k = len(x) - size({n: fixed[n] for n in refitting})  # the named effects' not again
    effects, error, aic, bic, passes = _judged(
        scene, held, noise, rollout, replay, x, replay.residuals(x), k, baseline
    )
    # A fit must never end worse than it started by the likelihood the BIC scores; one
    # that does failed, and is reported so rather than as an insignificant candidate.
    return CandidateResult(
        effect=name,
        params=effects[name],
        ci=replay.intervals_at(half_width)[name],
        heldout_error=error,
        aic=aic,
        bic=bic,
        delta_bic=bic - baseline.bic,
        significant=bool(passes and not replay.ended_worse),
        iterations=iterations,
        seconds=time.perf_counter() - started,
        fit_failed=replay.ended_worse,
        by_likelihood=replay.refit_by_likelihood,
    )


def refit(scene, fit_on, noise, selected, rollout) -> tuple[dict, list[dict]]:
    """Fit all named effects together, starting where they were named."""
    names = [s["effect"] for s in selected]
    start = {s["effect"]: s["params"] for s in selected}
    replay = WindowReplay(scene, fit_on, noise, free=names, start=start, pool=rollout)
    x, half_width, _ = replay.fit()
    effects, intervals = replay.effects_at(x), replay.intervals_at(half_width)
    refitted = [{"effect": n, "params": effects[n], "ci": intervals[n]} for n in names]
    return effects, refitted


def prune(
    scene, fit_on, held, noise, selected: list[dict], rollout
) -> tuple[dict, list[dict], dict[str, str]]:
    """The named effects without any that the others, refit without it, explain as well.

    Named one after another, an effect named early can stand in for part of one named
    later (a constant torque offset for a payload's weight over a narrow range of poses)
    and stay named once the later one explains it. Each is tried in the order named and
    dropped unless the set with it is significantly better (the naming rule) than the
    others refit without it. Returns the kept effects, their records and what was
    dropped with why."""
    fixed = {s["effect"]: s["params"] for s in selected}
    full = score(scene, fit_on, held, noise, fixed, rollout, size(fixed))
    dropped: dict[str, str] = {}
    for name in [s["effect"] for s in selected]:
        others = [s for s in selected if s["effect"] != name]
        if not others:
            break
        effects, refitted = refit(scene, fit_on, noise, others, rollout)
        without = score(scene, fit_on, held, noise, effects, rollout, size(effects))
        needed = (
            full.bic < without.bic - BIC_MARGIN
            and full.heldout_error <= (1 - MIN_HELDOUT_GAIN) * without.heldout_error
        )
        if not needed:
            kept = ", ".join(s["effect"] for s in others)
            dropped[name] = f"named, then explained as well by {kept} refit without it"
            selected, fixed, full = refitted, effects, without
    return fixed, selected, dropped
