"""What ``twinrl gap diagnose`` writes: gap_report.json, twin_fitted.yaml, report.md with
its plots, and overlay.rrd (measured, twin before and twin after, one held-out episode)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from twinrl_data.atomic import write_text_atomic
from twinrl_data.view import GHOST_ALPHA, log_cell_geometry, log_cell_poses
from twinrl_sim.build import compile_scene
from twinrl_sim.cell_view import TwinCell
from twinrl_sim.errors import TwinError
from twinrl_sim.gap.diagnose import AT_NOISE, FAR_ABOVE_NOISE, MIN_IMAGE_GAIN, Diagnosis
from twinrl_sim.gap.localize import Disagreement, plot_localization
from twinrl_sim.gap.search import BIC_MARGIN, MIN_HELDOUT_GAIN, SCREEN_KEEP
from twinrl_sim.spec import SceneSpec, save_spec

PLOTTED_SIGNALS = 4  # signals of the held-out overlay plot (largest gap first)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finite(value):
    """JSON has no infinity: an unbounded interval is written as null."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def report_json(diagnosis: Diagnosis, localization: list[Disagreement]) -> dict:
    return _finite(_report(diagnosis, localization))


def _report(diagnosis: Diagnosis, localization: list[Disagreement]) -> dict:
    d = diagnosis
    return {
        "candidates": [
            {k: v for k, v in r.to_dict().items() if k != "seconds"} for r in d.candidates
        ],
        "selected": d.selected,
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "heldout_reduction": d.heldout_reduction,
        "command_lag": d.command_lag,
        "arm_delay": d.arm_delay,
        "baseline": d.baseline,
        "rounds": [[r.to_dict() for r in rnd] for rnd in d.rounds],
        "signals": [
            {"signal": s, "unit": u, "heldout_rms_before": b, "heldout_rms_after": a}
            for s, u, b, a in zip(
                d.signals, d.units, d.heldout_rms_before, d.heldout_rms_after, strict=True
            )
        ],
        "image_gap": d.image_gap,
        "appearance_gap": d.appearance_gap,
        "inverse_dynamics": d.inverse_dynamics,
        "skipped": d.skipped,
        "dropped": d.dropped,
        "episodes": {"train": d.train_episodes, "heldout": d.heldout_episodes},
        "windows": d.windows,
        "split": d.split,
        "seconds": d.seconds,
        "localization": [r.to_dict() for r in localization],
    }


def write_fitted_spec(scene: SceneSpec, diagnosis: Diagnosis, path: Path) -> Path:
    """The twin with the named effects added, and where they came from."""
    fitted = scene.with_effects(diagnosis.effects)
    provenance = {
        **scene.provenance,
        "gap_diagnose": {
            "training_episodes": diagnosis.train_episodes,
            "heldout_episodes": diagnosis.heldout_episodes,
            "named": [
                {"effect": s["effect"], "params": s["params"], "ci95": _finite(s["ci"])}
                for s in diagnosis.selected
            ],
            "heldout_error_before": diagnosis.gap_before,
            "heldout_error_after": diagnosis.gap_after,
            "heldout_reduction": diagnosis.heldout_reduction,
            "error_unit": "RMS residual in sensor-noise units (1 = noise floor)",
        },
    }
    return save_spec(fitted.model_copy(update={"provenance": provenance}), path)


def plot_candidates(diagnosis: Diagnosis, path: Path) -> None:
    """Held-out error of each candidate, per round, against the twin without it."""
    plt = _pyplot()
    rounds = diagnosis.rounds
    fig, axes = plt.subplots(1, max(len(rounds), 1), figsize=(5 * max(len(rounds), 1), 4))
    axes = np.atleast_1d(axes)
    for i, (ax, results) in enumerate(zip(axes, rounds, strict=False)):
        names = [r.effect for r in results]
        errors = [r.heldout_error for r in results]
        colors = [
            "tab:green" if r.significant else "silver" if r.screened else "tab:gray"
            for r in results
        ]
        ax.barh(names[::-1], errors[::-1], color=colors[::-1])
        ax.set_xscale("log")
        ax.set_xlabel("held-out error (noise units, log)")
        ax.set_title(f"round {i + 1}: green significant, light screened")
        ax.axvline(1.0, color="k", lw=0.8, ls=":")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_signals(diagnosis: Diagnosis, path: Path) -> None:
    """Held-out RMS per signal before and after, one panel per unit."""
    plt = _pyplot()
    d = diagnosis
    units = list(dict.fromkeys(d.units))
    fig, axes = plt.subplots(1, len(units), figsize=(4.5 * len(units), 4))
    axes = np.atleast_1d(axes)
    for ax, unit in zip(axes, units, strict=True):
        idx = [i for i, u in enumerate(d.units) if u == unit]
        x = np.arange(len(idx))
        ax.bar(x - 0.2, [d.heldout_rms_before[i] for i in idx], 0.4, label="twin before")
        ax.bar(x + 0.2, [d.heldout_rms_after[i] for i in idx], 0.4, label="twin after")
        ax.set_xticks(x, [d.signals[i] for i in idx], rotation=60, ha="right")
        ax.set_yscale("log")
        ax.set_ylabel(f"held-out RMS ({unit})")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _overlay_rows(diagnosis: Diagnosis) -> tuple[np.ndarray, np.ndarray]:
    """Windows of the first held-out episode, in time order, and their row times (s)."""
    held = diagnosis.heldout
    first = held.episode.min()
    windows = np.flatnonzero(held.episode == first)
    windows = windows[np.argsort(held.start[windows])]
    return windows, (held.start[windows, None] + np.arange(1, held.rows + 1)) / held.fps


def _largest_gaps(diagnosis: Diagnosis, count: int) -> list[int]:
    d = diagnosis
    families = {u: [i for i, x in enumerate(d.units) if x == u] for u in set(d.units)}
    score = np.zeros(len(d.signals))
    for idx in families.values():
        before = np.array([d.heldout_rms_before[i] for i in idx])
        score[idx] = before / max(before.max(), 1e-12)
    return list(np.argsort(-score)[:count])


def plot_overlay(diagnosis: Diagnosis, path: Path) -> None:
    """Measured, twin before and twin after over one held-out episode (each window
    restarts from the measurement)."""
    plt = _pyplot()
    d = diagnosis
    windows, times = _overlay_rows(d)
    picks = _largest_gaps(d, PLOTTED_SIGNALS)
    fig, axes = plt.subplots(len(picks), 1, figsize=(10, 2.2 * len(picks)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, s in zip(axes, picks, strict=True):
        for k, w in enumerate(windows):
            label = k == 0
            ax.plot(times[k], d.heldout.measured[w, :, s], "k.", ms=3, label="measured" * label)
            ax.plot(times[k], d.predicted_before[w, :, s], "r-", lw=1, label="twin before" * label)
            ax.plot(times[k], d.predicted_after[w, :, s], "g-", lw=1, label="twin after" * label)
        ax.set_ylabel(f"{d.signals[s]} ({d.units[s]})", fontsize=8)
    axes[0].legend(fontsize=7, ncol=3)
    axes[-1].set_xlabel("time (s); the twin restarts from the measurement every window")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_overlay_rrd(diagnosis: Diagnosis, path: Path, scene: SceneSpec | None = None) -> None:
    """A Rerun recording of one held-out episode: every compared signal as measured,
    twin before and twin after, the three TCP paths and, given the twin's ``scene`` and
    logged joints, the arm in 3D three times: measured, and the twin before and after
    as translucent ghosts over it."""
    d = diagnosis
    windows, times = _overlay_rows(d)
    recording = rr.RecordingStream("twinrl_gap_overlay")
    recording.save(str(path))
    cell = _overlay_cell(scene, d.signals)
    if cell is not None:
        for label in ("measured", "twin_before", "twin_after"):
            opacity = 255 if label == "measured" else GHOST_ALPHA
            log_cell_geometry(cell, f"world/{label}/cell", recording, opacity)
    tcp = [d.signals.index(n) for n in ("tcp.x", "tcp.y", "tcp.z")]
    series = {
        "measured": d.heldout.measured,
        "twin_before": d.predicted_before,
        "twin_after": d.predicted_after,
    }
    colors = {"measured": [20, 20, 20], "twin_before": [220, 50, 47], "twin_after": [40, 160, 60]}
    for name in d.signals:
        for label in series:
            rr.log(
                f"signals/{name}/{label}",
                rr.SeriesLines(colors=[colors[label]], names=f"{name} {label}"),
                static=True,
                recording=recording,
            )
    paths: dict[str, list] = {label: [] for label in series}
    for k, w in enumerate(windows):
        for r, t in enumerate(times[k]):
            recording.set_time("time", duration=float(t))
            for label, values in series.items():
                for s, name in enumerate(d.signals):
                    rr.log(
                        f"signals/{name}/{label}",
                        rr.Scalars(float(values[w, r, s])),
                        recording=recording,
                    )
                if cell is not None:
                    log_cell_poses(cell, f"world/{label}/cell", values[w, r], None, recording)
                paths[label].append(values[w, r, tcp].tolist())
                rr.log(
                    f"world/{label}/tcp_path",
                    rr.LineStrips3D([paths[label]], colors=[colors[label]]),
                    recording=recording,
                )
    views = [
        rrb.TimeSeriesView(origin=f"signals/{d.signals[s]}", name=d.signals[s])
        for s in _largest_gaps(d, PLOTTED_SIGNALS)
    ]
    recording.send_blueprint(
        rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="world"), rrb.Vertical(*views)))
    )
    recording.flush()
    recording.disconnect()


def _overlay_cell(scene: SceneSpec | None, signals: list[str]) -> TwinCell | None:
    """The twin's cell posed by the compared signals, when they hold every arm joint."""
    if scene is None:
        return None
    try:
        return TwinCell(compile_scene(scene), signals)
    except TwinError:  # the diagnosis compared no joint angles: no arm to pose
        return None


def verdict(before: float, after: float, named: bool, localization: list[Disagreement]) -> str:
    """One paragraph on how far the twin still is from the log, and where it disagrees
    most, so that a large gap nothing explains is never reported as if all were well."""
    if after <= AT_NOISE:
        return (
            f"**The twin explains the held-out data** to the sensor noise ({after:.3g} noise "
            "units left)."
        )
    where = "; ".join(
        f"`{r.signal}` {r.rms:.2g} {r.unit} RMS"
        + (f", worst when {max(r.regimes, key=r.regimes.get)}" if r.regimes else "")
        + (f", lagging {1000 * r.lag_s:+.0f} ms" if abs(r.lag_s) > 0 else "")
        for r in localization[:3]
    )
    kinds = {_signal_kind(r.signal) for r in localization[:3]}
    if after <= FAR_ABOVE_NOISE:
        return (
            f"**Close, not exact**: {after:.3g} noise units are left. Largest disagreements: "
            f"{where or 'none localised'}."
        )
    status = "even with the named effects" if named else "and no candidate explains it"
    return (
        f"**The twin is far off**: the held-out error is {after:.3g} times the sensor noise "
        f"({before:.3g} before), {status}. It disagrees most in {', '.join(sorted(kinds))}: "
        f"{where or 'see the localisation below'}. Look for what the effects library does "
        "not model there: the cell's geometry (base mounting, tool frame), the servo's "
        "tracking, a load; `twinrl gap localize` shows each signal by motion regime."
    )


def _signal_kind(signal: str) -> str:
    if signal.startswith("tcp."):
        return "the TCP frame"
    if signal.startswith(("tau", "effort")):
        return "the joint torques"
    return "the joint motion"


def write_markdown(diagnosis: Diagnosis, localization: list[Disagreement], path: Path) -> None:
    d = diagnosis
    lines = [
        "# Sim-to-real gap diagnosis",
        "",
        f"{d.split[0].upper()}{d.split[1:]}; {d.windows['fitted']} of {d.windows['train']} "
        f"training windows fitted; {d.seconds:.0f} s.",
        "",
        "## Named effects",
        "",
    ]
    if d.selected:
        lines += ["| order | effect | parameters | 95 % interval (±) |", "|---|---|---|---|"]
        for i, s in enumerate(d.selected, 1):
            params, ci = format_params(s["params"]), format_params(s["ci"])
            lines.append(f"| {i} | {s['effect']} | {params} | {ci} |")
    else:
        lines.append("None: no candidate beats the twin as it is on held-out data.")
    if d.command_lag is not None:
        lines += ["", command_lag_line(d)]
    lines += ["", verdict(d.gap_before, d.gap_after, bool(d.selected), localization)]
    lines += [
        "",
        f"**Held-out error** (RMS residual in sensor-noise units, 1 = noise floor): "
        f"{d.gap_before:.3g} before, {d.gap_after:.3g} after "
        f"({100 * d.heldout_reduction:.1f} % smaller). The fitted twin is `twin_fitted.yaml`; "
        "`overlay.rrd` overlays measured, twin before and twin after (open it with "
        "`rerun overlay.rrd`).",
        "",
        "![held-out signals](overlay.png)",
        "",
        "## Candidates",
        "",
        f"A candidate is significant when its BIC beats the twin without it by more than "
        f"{BIC_MARGIN:g} and it cuts the held-out error by at least "
        f"{100 * MIN_HELDOUT_GAIN:.0f} %. Each round takes one Gauss-Newton step of every "
        f"candidate and fits the {SCREEN_KEEP} whose step explains most; the others are "
        "shown at their step (screened). Intervals assume independent residuals and are "
        "therefore optimistic.",
        "",
    ]
    baseline = d.baseline
    for i, results in enumerate(d.rounds, 1):
        lines += [
            f"### Round {i}",
            "",
            "| effect | parameters | 95 % (±) | held-out error | AIC | BIC | ΔBIC | significant |",
            "|---|---|---|---|---|---|---|---|",
        ]
        if i == 1:
            lines.append(
                f"| (twin as it is) | | | {baseline['heldout_error']:.3g} | "
                f"{baseline['aic']:.0f} | {baseline['bic']:.0f} | | |"
            )
        for r in results:
            lines.append(
                f"| {r.effect} | {format_params(r.params)} | {format_params(r.ci)} | "
                f"{r.heldout_error:.3g} | "
                f"{r.aic:.0f} | {r.bic:.0f} | {r.delta_bic:+.0f} | "
                f"{_verdict(r)} |"
            )
        lines.append("")
    if d.cameras:
        lines += [
            "### Cameras",
            "",
            "`camera_pose` per camera, judged on image residuals (the twin's render at the "
            f"measured state against the logged image, grey, standardised; noise unit "
            f"{d.image_noise:g}); significant when BIC improves by more than {BIC_MARGIN:g} and "
            f"the held-out image error drops by at least {100 * MIN_IMAGE_GAIN:.0f} %. "
            "A shift across the view and a small turn look alike from "
            "one camera over a shallow scene: the fitted pose is the one the images support.",
            "",
            "| camera | parameters | 95 % (±) | held-out image error before | after | ΔBIC "
            "| significant |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in d.cameras:
            camera = r.params["camera"]
            shown = {k: v for k, v in r.params.items() if k != "camera"}
            lines.append(
                f"| {camera} | {format_params(shown)} | {format_params(r.ci)} | "
                f"{d.image_gap[camera]['before']:.3g} | {r.heldout_error:.3g} | "
                f"{r.delta_bic:+.0f} | {'yes' if r.significant else 'no'} |"
            )
        lines.append("")
    if d.appearance is not None:
        r, gap = d.appearance, d.appearance_gap
        lines += [
            "### Appearance",
            "",
            "`appearance` (light intensity, table colour) on every logged camera's colours "
            f"(box-averaged RGB, 0-1; noise unit {d.colour_noise:g}), judged by the same rule "
            "as the cameras. Image policies trained on twin renders need the twin to look "
            "like the cell.",
            "",
            "| compared | parameters | 95 % (±) | held-out colour error before | after | ΔBIC "
            "| significant |",
            "|---|---|---|---|---|---|---|",
            f"| {r.compared.partition(':')[2]} | {format_params(r.params)} | "
            f"{format_params(r.ci)} | {gap['before']:.3g} | {r.heldout_error:.3g} | "
            f"{r.delta_bic:+.0f} | {'yes' if r.significant else 'no'} |",
            "",
        ]
    if d.skipped:
        lines += ["Not fitted: " + "; ".join(f"{k} ({v})" for k, v in d.skipped.items()), ""]
    if d.dropped:
        lines += ["Dropped: " + "; ".join(f"{k} ({v})" for k, v in d.dropped.items()), ""]
    lines += [
        "![candidates](candidates.png)",
        "",
        "## Held-out error per signal",
        "",
        "| signal | before | after | unit |",
        "|---|---|---|---|",
    ]
    for s, u, b, a in zip(
        d.signals, d.units, d.heldout_rms_before, d.heldout_rms_after, strict=True
    ):
        lines.append(f"| {s} | {b:.3g} | {a:.3g} | {u} |")
    lines += ["", "![signals](signals.png)", ""]
    if d.inverse_dynamics:
        lines += [
            "## Inverse dynamics on held-out episodes",
            "",
            "Measured joint torques against the torques the twin needs for the measured "
            "motion (contacts off, so a held object's load counts as disagreement); RMS.",
            "",
            "| signal | before | after | unit |",
            "|---|---|---|---|",
        ]
        for signal, gap in d.inverse_dynamics.items():
            lines.append(f"| {signal} | {gap['before']:.3g} | {gap['after']:.3g} | N m |")
        lines.append("")
    lines += [
        "## Where the twin disagreed (before)",
        "",
        "| signal | RMS | bias | gain | lag (ms) | worst regime |",
        "|---|---|---|---|---|---|",
    ]
    for r in localization:
        worst = max(r.regimes, key=r.regimes.get) if r.regimes else "-"
        lines.append(
            f"| {r.signal} | {r.rms:.2e} {r.unit} | {r.bias:+.2e} | {r.gain:.3f} | "
            f"{1000 * r.lag_s:+.0f} | {worst} |"
        )
    lines += ["", "![localization](localization.png)", ""]
    write_text_atomic(path, "\n".join(lines))


def command_lag_line(diagnosis: Diagnosis) -> str:
    """The command link's measured lag, and the arm's own delay where one was named."""
    lag = 1000 * diagnosis.command_lag
    line = (
        f"The controller's servo targets trailed the logged joint targets by {lag:.1f} ms "
        "(measured from the targets it echoed: host, network, servo period, servoJ)"
    )
    if diagnosis.arm_delay is None:
        return line + "."
    total = 1000 * diagnosis.effects["actuator_delay"]["seconds"]
    return (
        f"{line}; of the named {total:.1f} ms actuator delay, the arm's own is "
        f"{1000 * diagnosis.arm_delay:.1f} ms. The fitted twin keeps the whole delay: it is "
        "driven by the host's commands."
    )


def format_params(params: dict) -> str:
    """``mass 2; scale [0.6, 0.6, ...]`` for tables (3 significant digits)."""
    parts = []
    for key, value in params.items():
        if isinstance(value, list):
            parts.append(f"{key} [{', '.join(f'{v:.3g}' for v in value)}]")
        elif isinstance(value, str):
            parts.append(f"{key} {value}")
        else:
            parts.append(f"{key} {value:.3g}")
    return "; ".join(parts)


def write_report(
    diagnosis: Diagnosis,
    localization: list[Disagreement],
    scene: SceneSpec,
    out: Path,
) -> None:
    """Every output of ``twinrl gap diagnose`` into ``out`` (which must be new or empty)."""
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(
        out / "gap_report.json", json.dumps(report_json(diagnosis, localization), indent=1)
    )
    write_fitted_spec(scene, diagnosis, out / "twin_fitted.yaml")
    plot_candidates(diagnosis, out / "candidates.png")
    plot_signals(diagnosis, out / "signals.png")
    plot_overlay(diagnosis, out / "overlay.png")
    plot_localization(localization, out / "localization.png")
    write_overlay_rrd(diagnosis, out / "overlay.rrd", scene)
    write_markdown(diagnosis, localization, out / "report.md")


def _verdict(result) -> str:
    """A candidate's significance column; a fit that ended worse than it started, or was
    refit on the likelihood's bound because its squares' fit did, says so."""
    if result.fit_failed:
        return "no: its fit ended worse than it started"
    if result.screened:
        return "no: screened (one step; others explained more)"
    verdict = "yes" if result.significant else "no"
    if result.by_likelihood:
        verdict += " (fitted on the likelihood's bound: its squares' fit ended worse)"
    return verdict
