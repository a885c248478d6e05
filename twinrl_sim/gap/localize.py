"""Where measured and replayed signals disagree: per signal and joint, per phase and
motion regime, with time lag, bias and gain. Signals are the forward replay's joints,
velocities and TCP position and, when torques are logged, the measured torques against
the inverse dynamics of the measured motion (``tau_id.*``).

- **lag**: the shift (s, sub-step by parabolic interpolation) that best aligns the
  measured joint motion with the replayed one (cross-correlation of the per-step
  increments); positive when the measurement trails the twin (a delay the twin lacks);
- **bias**: mean of measured minus replayed (an offset, a sag under gravity);
- **gain**: least-squares slope of the measured excursion against the replayed one
  about their means (1 when the twin moves as much as the robot);
- **regimes**: near-zero velocity, velocity reversals, high acceleration, static holds
  and the rest (free motion), and phases by the gripper command (open: free motion,
  closed: grasp/transport).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from twinrl_sim.errors import TwinError
from twinrl_sim.gap.inverse import PREFIX as INVERSE_PREFIX
from twinrl_sim.gap.shooting import ShootingReplay

# signal prefixes compared, and units
UNITS = {"q.": "rad", "qd.": "rad/s", "tcp.": "m", INVERSE_PREFIX: "N m"}
TCP_POSITION = ("tcp.x", "tcp.y", "tcp.z")
SLOW = 0.02  # rad/s: "near-zero velocity"
MAX_LAG = 5  # steps searched either side


@dataclass
class Disagreement:
    """One row of the localisation table."""

    signal: str  # e.g. q.elbow, tcp.z
    unit: str
    rms: float
    bias: float
    gain: float
    lag_s: float
    regimes: dict[str, float]  # RMS per regime/phase (rows in it > 0)

    def to_dict(self) -> dict:
        return asdict(self)


def _lag(measured: np.ndarray, predicted: np.ndarray, valid: np.ndarray, fps: float) -> float:
    """Lag (s) maximising the correlation of measured and predicted increments."""
    dm = np.where(valid, np.diff(measured, prepend=measured[0]), 0.0)
    dp = np.where(valid, np.diff(predicted, prepend=predicted[0]), 0.0)
    if not dm.any() or not dp.any():
        return 0.0
    scores = np.array(
        [
            np.dot(dm[max(k, 0) : len(dm) + min(k, 0)], dp[max(-k, 0) : len(dp) - max(k, 0)])
            for k in range(-MAX_LAG, MAX_LAG + 1)
        ]
    )
    best = int(np.argmax(scores))
    shift = float(best - MAX_LAG)
    if 0 < best < len(scores) - 1:  # parabolic refinement
        a, b, c = scores[best - 1 : best + 2]
        denom = a - 2 * b + c
        if denom < 0:
            shift += 0.5 * (a - c) / denom
    return shift / fps


def _within(replay: ShootingReplay, prefix: str) -> np.ndarray:
    """Rows whose increment from the row before stays inside one forward-replay window
    (inverse dynamics has no windows)."""
    if prefix == INVERSE_PREFIX:
        return np.ones(len(replay.measured), bool)
    return replay.step_in_window > 1


def _regimes(replay: ShootingReplay, joint: str | None) -> dict[str, np.ndarray]:
    """Boolean row masks of each regime (for a joint's own velocity when it has one)."""
    names = replay.names
    qd_cols = replay.columns("qd.")
    if joint is not None and f"qd.{joint}" in names:
        speed = replay.measured[:, names.index(f"qd.{joint}")]
    elif qd_cols:
        speed = np.abs(replay.measured[:, qd_cols]).max(1)
    else:
        q = replay.measured[:, replay.columns("q.")]
        speed = np.abs(np.gradient(q, axis=0) * replay.fps).max(1)
    accel = np.abs(np.gradient(speed) * replay.fps)
    reversal = np.zeros(len(speed), bool)
    flips = np.flatnonzero(np.sign(speed[1:]) * np.sign(speed[:-1]) < 0)
    for i in flips:
        reversal[max(i - 1, 0) : i + 3] = True
    moving_target = (
        np.abs(np.diff(replay.targets, axis=0, prepend=replay.targets[:1])).max(1) > 1e-4
    )
    slow = np.abs(speed) < SLOW
    high_accel = accel > np.quantile(accel, 0.9) if len(accel) > 10 else np.zeros_like(slow)
    static = slow & ~moving_target
    closed = replay.gripper > 0.5
    return {
        "near_zero_velocity": slow & ~static,
        "reversal": reversal,
        "high_acceleration": high_accel,
        "static_hold": static,
        "free_motion": ~closed & ~slow & ~reversal & ~high_accel,
        "grasp_transport": closed,
    }


def localize(replays: list[ShootingReplay]) -> list[Disagreement]:
    """The localisation table over several episodes, largest RMS (in each unit) first."""
    if not replays:
        raise TwinError("no episodes to compare")
    rows = []
    names = replays[0].names
    for i, name in enumerate(names):
        prefix = next((p for p in UNITS if name.startswith(p)), None)
        if prefix is None or (prefix == "tcp." and name not in TCP_POSITION):
            continue
        joint = name.split(".", 1)[1] if prefix != "tcp." else None
        measured = np.concatenate([r.measured[:, i] for r in replays])
        predicted = np.concatenate([r.predicted[:, i] for r in replays])
        regimes = [_regimes(r, joint) for r in replays]
        error = measured - predicted
        dm = measured - measured.mean()
        dp = predicted - predicted.mean()
        gain = float(np.dot(dm, dp) / np.dot(dp, dp)) if np.dot(dp, dp) > 0 else 1.0
        lags = [
            # A forward replay's increments are its own within a window (not across a restart).
            _lag(r.measured[:, i], r.predicted[:, i], _within(r, prefix), r.fps)
            for r in replays
        ]
        per_regime = {}
        for regime in regimes[0]:
            mask = np.concatenate([m[regime] for m in regimes])
            if mask.any():
                per_regime[regime] = float(np.sqrt(np.mean(error[mask] ** 2)))
        rows.append(
            Disagreement(
                signal=name,
                unit=UNITS[prefix],
                rms=float(np.sqrt(np.mean(error**2))),
                bias=float(error.mean()),
                gain=gain,
                lag_s=float(np.median(lags)),
                regimes=per_regime,
            )
        )
    return sorted(rows, key=lambda r: (r.unit, -r.rms))


def plot_localization(rows: list[Disagreement], path: Path) -> None:
    """RMS per signal by regime (one panel per unit) and the lag per signal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    units = sorted({r.unit for r in rows})
    fig, axes = plt.subplots(1, len(units) + 1, figsize=(5 * (len(units) + 1), 4))
    for ax, unit in zip(axes, units, strict=False):
        group = [r for r in rows if r.unit == unit]
        regimes = sorted({k for r in group for k in r.regimes})
        width = 0.8 / max(len(regimes), 1)
        for k, regime in enumerate(regimes):
            ax.bar(
                np.arange(len(group)) + k * width,
                [r.regimes.get(regime, 0) for r in group],
                width,
                label=regime,
            )
        ax.set_xticks(
            np.arange(len(group)) + 0.4 - width / 2,
            [r.signal for r in group],
            rotation=60,
            ha="right",
        )
        ax.set_ylabel(f"RMS ({unit})")
        ax.set_title(f"disagreement ({unit})")
        ax.legend(fontsize=7)
    joints = [r for r in rows if r.signal.startswith("q.")]
    axes[-1].bar([r.signal for r in joints], [1000 * r.lag_s for r in joints])
    axes[-1].set_ylabel("lag (ms): measurement behind twin")
    axes[-1].tick_params(axis="x", rotation=60)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
