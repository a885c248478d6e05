"""The pipeline's report: each method's curves, minutes to 95 %, per-seed tables, and
a representative episode in Rerun."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data.atomic import write_text_atomic
from twinrl_data.catalog import build_index
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_data.view import save_rrd
from twinrl_learn.evaluate import grid_cells
from twinrl_learn.real_rl_progress import EvalPoint, kept_start, load_evaluations, minutes_to
from twinrl_learn.studies.layout import eval_folder
from twinrl_learn.studies.presets import METHOD_TABLE, Preset
from twinrl_sim.tasks import REGION_NAMES


def _median(values: list[float | None]) -> float | None:
    """Median where a missing value (never reached) counts as infinitely late."""
    finite = [math.inf if v is None else v for v in values]
    middle = float(np.median(finite))
    return None if math.isinf(middle) else middle


def method_summary(folders: dict[int, Path]) -> dict[str, Any]:
    """One method's ``M`` of report.json: medians over its seeds."""
    per_seed = []
    for folder in folders.values():
        evaluations = load_evaluations(folder)
        history = json.loads((folder / "run.json").read_text())["history"]
        per_seed.append(
            {
                "to95": {r: minutes_to(evaluations, r) for r in REGION_NAMES},
                "final": evaluations[-1].success_rate,
                "interventions": sum(h["interventions"] for h in history),
                "plant_steps": history[-1]["env_steps"] if history else 0,
                "kept": {r: kept_start(evaluations, r) for r in REGION_NAMES},
            }
        )
    return {
        "plant_minutes_to_95": {r: _median([s["to95"][r] for s in per_seed]) for r in REGION_NAMES},
        "final_success": {
            r: float(np.median([s["final"].get(r, 0.0) for s in per_seed])) for r in REGION_NAMES
        },
        "interventions": int(np.median([s["interventions"] for s in per_seed])),
        "plant_steps": int(np.median([s["plant_steps"] for s in per_seed])),
        # seeds that ended at least where they started, the last within noise of the best
        "seeds_kept_start": {r: sum(s["kept"][r] for s in per_seed) for r in REGION_NAMES},
    }


def _curve(evaluations: list[EvalPoint], region: str, grid: np.ndarray) -> np.ndarray:
    """Success held from each evaluation until the next, on ``grid`` (plant minutes)."""
    xs = np.array([e.plant_minutes for e in evaluations])
    ys = np.array([e.success_rate.get(region, 0.0) for e in evaluations])
    index = np.searchsorted(xs, grid, side="right") - 1
    return ys[np.clip(index, 0, len(ys) - 1)]


def plot_methods(runs: dict[str, dict[int, Path]], path: Path, title: str) -> None:
    """Evaluation success in ID and OOD against plant minutes: median over seeds (bold),
    each seed (thin)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), dpi=120, sharey=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, region in zip(axes, REGION_NAMES, strict=True):
        for color, (name, folders) in zip(colors, runs.items(), strict=False):
            series = [load_evaluations(f) for f in folders.values()]
            end = max(s[-1].plant_minutes for s in series)
            grid = np.linspace(0, end, 200)
            curves = np.array([_curve(s, region, grid) for s in series])
            for curve in curves:
                ax.plot(grid, curve, color=color, lw=0.6, alpha=0.35)
            ax.plot(grid, np.median(curves, axis=0), color=color, lw=2, label=name)
        ax.axhline(0.95, color="grey", lw=0.8, ls="--")
        ax.set_title(f"{region}", fontsize=10)
        ax.set_xlabel("plant minutes")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("evaluation success")
    axes[0].set_ylim(-0.02, 1.02)
    axes[1].legend(fontsize=8, loc="lower right")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _fmt_minutes(value: float | None) -> str:
    return "not reached" if value is None else f"{value:.1f}"


def _pct(rate: float) -> str:
    return f"{100 * rate:.0f} %"


def _with_interval(point: EvalPoint, region: str) -> str:
    """``94 % (85–98)``: the rate and its 95 % interval, where the episodes are known."""
    rate = point.success_rate.get(region, 0.0)
    interval = point.interval(region)
    if interval is None:
        return _pct(rate)
    return f"{_pct(rate)} ({100 * interval[0]:.0f}–{100 * interval[1]:.0f})"


def _per_seed_table(runs: dict[str, dict[int, Path]]) -> list[str]:
    """Markdown rows: one per method and seed, one column per evaluation."""
    series = {
        (name, seed): load_evaluations(folder)
        for name, folders in runs.items()
        for seed, folder in folders.items()
    }
    columns = max(len(s) for s in series.values())
    longest = max(series.values(), key=len)
    header = " | ".join(f"~{e.plant_minutes:.1f} min" for e in longest)
    rows = [f"| method | seed | {header} |", "|---|---|" + "---|" * columns]
    for (name, seed), evaluations in series.items():
        cells = [" / ".join(_with_interval(e, r) for r in REGION_NAMES) for e in evaluations]
        rows.append(
            f"| {name} | {seed} | " + " | ".join(cells + [""] * (columns - len(cells))) + " |"
        )
    return rows


def write_report(
    task: str,
    preset_name: str,
    p: Preset,
    out: Path,
    stage1: dict[str, Path],
    runs: dict[str, dict[int, Path]],
    seeds: tuple[int, ...],
) -> dict[str, Any]:
    methods = {name: method_summary(folders) for name, folders in runs.items()}
    twin_data = f"{p.real_demos} real + {p.twin_id} ID / {p.twin_ood} OOD twin demos"
    starts = [  # (report.json key, what it is, its plant evaluation)
        (
            "sft_real",
            f"Stage I: SFT on real demos only ({p.real_demos} real)",
            eval_folder(stage1["sft_real"]),
        ),
        (
            "sft_real_twin",
            f"Stage I: SFT on {twin_data}",
            eval_folder(stage1["sft_twin"]),
        ),
        (
            "twin_rl",
            f"Stage II: twin RL ({p.twin_rl_steps} twin steps)",
            out / "stage2" / "plant_eval",
        ),
    ]
    start_rates = {}
    for key, _, folder in starts:
        rates = json.loads((folder / "eval.json").read_text())["success_rate"]
        start_rates[key] = {r: rates.get(r, 0.0) for r in REGION_NAMES}
    report = {
        "task": task,
        "preset": preset_name,
        "policy": p.policy,
        "inputs": p.inputs,
        "seeds": list(seeds),
        "stages": start_rates,
        "methods": methods,
    }
    write_text_atomic(out / "report.json", json.dumps(report, indent=1))
    plot_methods(runs, out / "curves.png", f"{task}: real RL in the plant ({preset_name})")
    per_region = " / ".join(
        str(sum(c.region == region for c in grid_cells(task, p.eval_grid)) * p.eval_episodes)
        for region in REGION_NAMES
    )
    lines = [
        f"# TwinRL in the plant: {task}, preset `{preset_name}`",
        "",
        f"Policy: **{p.policy}**"
        + (
            f" (privileged object poses instead of images; {p.inputs} inputs)"
            if p.policy == "state"
            else ""
        )
        + f". Seeds: {', '.join(map(str, seeds))}. Real RL: {p.plant_steps} robot steps "
        f"({p.plant_steps / 600:.1f} plant minutes) per run; evaluation every {p.eval_every} "
        f"steps on a {p.eval_grid[0]}x{p.eval_grid[1]} grid ({per_region} episodes in "
        f"{' / '.join(REGION_NAMES)}) in a separate plant (not counted as interaction). "
        "Values are medians over seeds.",
        "",
        _what_it_reads(p),
        "",
        "## The starting policies (plant evaluation, same grid)",
        "",
        "HiL-SERL and ConRFT-style start from the real-only SFT policy, both TwinRL "
        "variants from the Stage II policy.",
        "",
        "| policy | ID | OOD |",
        "|---|---|---|",
        *[
            f"| {label} | {_pct(start_rates[key]['ID'])} | {_pct(start_rates[key]['OOD'])} |"
            for key, label, _ in starts
        ],
        "",
        "## Real RL",
        "",
        "![success against plant minutes](curves.png)",
        "",
        "| method | minutes to 95 % ID | minutes to 95 % OOD | final ID | final OOD "
        "| seeds that kept their start, ID / OOD | intervention steps | robot steps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, m in methods.items():
        kept = " / ".join(f"{m['seeds_kept_start'][r]} of {len(seeds)}" for r in REGION_NAMES)
        lines.append(
            f"| {name} | {_fmt_minutes(m['plant_minutes_to_95']['ID'])} "
            f"| {_fmt_minutes(m['plant_minutes_to_95']['OOD'])} "
            f"| {100 * m['final_success']['ID']:.0f} % | {100 * m['final_success']['OOD']:.0f} % "
            f"| {kept} | {m['interventions']} | {m['plant_steps']} |"
        )
    lines += [
        "",
        "A seed kept its start when its last evaluation is at least its first and its best "
        "lies within the last's 95 % interval (noise, not a loss).",
        "",
        "Each run's evaluations, ID / OOD, with each rate's 95 % Wilson interval in "
        "brackets (an evaluation follows the episode that crosses its step count, so the "
        "minutes differ a little between runs):",
        "",
    ]
    lines += _per_seed_table(runs)
    lines += [
        "",
        "Per run: `real_rl/<method>/seed<k>/` (curve.png, evaluations/, session/, "
        "live-*.rrd). All episodes are indexed in `catalog.parquet`; "
        "`representative.rrd` shows a TwinRL episode with an operator takeover and its "
        "last training episode.",
        "",
        "Settings: " + json.dumps(asdict(p)),
    ]
    write_text_atomic(out / "report.md", "\n".join(lines) + "\n")
    build_index([out], out / "catalog.parquet")
    _representative(runs[METHOD_TABLE[0].name], out / "representative.rrd")
    return report


def _what_it_reads(p: Preset) -> str:
    """Whether the runs read state only the plant knows, and what stands in for it."""
    if not p.privileged:
        return (
            "**Nothing privileged**: the image policy acts through a pose estimator trained "
            f"on twin renders ({p.perception} twin episodes per region), a classifier trained "
            f"on twin episodes ({p.classifier_episodes} per region) judges each real-RL "
            "episode's success, and the simulated person decides from the estimator's view; "
            "the plant's truth only scores the evaluations."
        )
    return (
        "**Privileged reference** (a real cell has none of this): "
        + "; ".join(p.privileged_reads())
        + "."
    )


def _representative(folders: dict[int, Path], path: Path) -> None:
    session = Session(next(iter(folders.values())) / "session")
    entries, paths = session.entries, session.episode_paths()
    helped = [p for p, e in zip(paths, entries, strict=True) if e.get("num_interventions")]
    chosen = ([helped[-1]] if helped else []) + [paths[-1]]
    save_rrd([read_episode(p) for p in dict.fromkeys(chosen)], path, force=True)
