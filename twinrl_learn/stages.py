"""What each TwinRL stage adds, measured more precisely than a pipeline run can.

A ``twinrl demo`` run evaluates its policies as it goes, on one grid (32 episodes per
region in the quick preset, so a rate near 80 % is known to about ±7 points): too few
to tell stages or the twin buffer apart. This study measures a finished run's policies
again on many more plant episodes, every policy on the same configurations (evaluation
``k`` of every policy uses plant seed ``EVAL_SEED + k``, so differences are paired):

- the two Stage I SFT policies (real demos only; real + twin demos);
- the Stage II policy (twin RL);
- the Stage II policy after the real-RL offline phase (Cal-QL + imitation, before any
  robot step) with the twin buffer in the replay buffer and without it, once per seed
  ``k``: what the twin buffer changes before the robot moves (the paper reports the
  smallest dip at the offline-to-online switch for TwinRL);
- the final policies of the run's TwinRL and TwinRL-without-twin-buffer runs.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twinrl_learn.evaluate import evaluate
from twinrl_learn.policy import Policy
from twinrl_learn.real_rl import RealRL, RealRLSettings
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.settings import RLConfig
from twinrl_sim.tasks import REGION_NAMES

EVAL_SEED = 20_000  # apart from the pipeline's own evaluations (10_000 + ...)
WITH_BUFFER = "Stage II + offline phase, with the twin buffer"
WITHOUT_BUFFER = "Stage II + offline phase, without the twin buffer"
TWIN_RL_RUNS = {"twinrl": "TwinRL", "twinrl_no_buffer": "TwinRL w/o twin buffer"}


@dataclass(frozen=True)
class StagesSettings:
    run: Path  # a finished (or stopped after Stage II) `twinrl demo` run
    out: Path
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)  # evaluation seeds and offline-phase seeds
    grid: tuple[int, int] = (8, 8)
    episodes: int = 2  # per grid cell and evaluation
    finals: bool = True  # also the final policies of the run's TwinRL runs


@dataclass(frozen=True)
class _Candidate:
    label: str
    checkpoint: Path | None  # None: made per seed by the offline phase
    twin_buffer: bool = False


def _candidates(run: Path, finals: bool) -> list[_Candidate]:
    """The run's policies to measure, checked to exist (a clear error if not)."""
    if not (run / "run.json").is_file():
        raise ValueError(f"{run} is not a `twinrl demo` run folder (no run.json)")
    sft = sorted(p for p in (run / "stage1").glob("*_real_twin") if p.is_dir())
    stage2 = run / "stage2"
    if not sft or not (stage2 / ".done").is_file():
        raise ValueError(
            f"{run} has not finished Stage II; continue it with `twinrl demo --out {run} "
            "--resume` first"
        )
    real_only = sft[0].with_name(sft[0].name.removesuffix("_twin"))
    candidates = [
        _Candidate("Stage I: SFT, real demos only", real_only),
        _Candidate("Stage I: SFT, real + twin demos", sft[0]),
        _Candidate("Stage II: twin RL", stage2 / "agent"),
        _Candidate(WITHOUT_BUFFER, None),
    ]
    if (stage2 / "twin_buffer" / "meta" / "info.json").is_file():  # no rollout kept: none
        candidates.insert(3, _Candidate(WITH_BUFFER, None, twin_buffer=True))
    if finals:
        for slug, name in TWIN_RL_RUNS.items():
            for folder in sorted((run / "real_rl" / slug).glob("seed*")):
                if (folder / ".done").is_file():
                    candidates.append(_Candidate(f"{name}, {folder.name} final", folder / "agent"))
    return candidates


def _offline_policy(run: Path, out: Path, seed: int, twin_buffer: bool) -> Policy:
    """The Stage II policy after the offline phase of a TwinRL real-RL run (seed ``seed``),
    exactly as the pipeline starts it, with or without the twin buffer."""
    task = json.loads((run / "run.json").read_text())["task"]
    template = run / "real_rl" / "twinrl" / "seed0" / "agent"
    if (template / "rl_config.json").is_file():  # the settings the TwinRL runs had
        rl = RLConfig.load(template)
    else:  # the run stopped before real RL: the pipeline's settings
        rl = RLConfig.for_method("twinrl", offline_steps=_preset_offline_steps(run))
    settings = RealRLSettings(
        task=task,
        init=str(run / "stage2" / "agent"),
        out=str(out),
        demos=[str(run / "stage1" / "real"), str(run / "stage1" / "twin" / "dataset")],
        twin_buffer=str(run / "stage2" / "twin_buffer") if twin_buffer else None,
        show_resets=False,
        rl=replace(rl, seed=seed),
    )
    real = RealRL.start(settings)
    try:
        real.run_state.pretrain()
    finally:
        real.close()
    return real.run_state.agent.policy


def _preset_offline_steps(run: Path) -> int:
    from twinrl_learn.pipeline import PRESETS

    recorded = json.loads((run / "run.json").read_text())
    preset = recorded["preset"]
    if "settings" in recorded:  # a custom preset (run_demo with a Preset)
        return recorded["settings"]["offline_steps"]
    if preset not in PRESETS:
        raise ValueError(f"{run} was made with preset '{preset}', which this version lacks")
    return PRESETS[preset].offline_steps


def measure_stages(
    settings: StagesSettings,
    on_evaluation: Callable[[int, int, str], None] | None = None,
) -> dict[str, object]:
    """Measure every candidate policy of ``settings.run``; write ``stages.json``,
    ``stages.md`` and ``stages.png`` to ``settings.out``; return the JSON's content.
    ``on_evaluation(done, total, label)`` hears before each evaluation."""
    s = settings
    if not s.seeds:
        raise ValueError("--seeds needs at least one seed")
    if s.episodes < 1:
        raise ValueError(f"--episodes must be at least 1, got {s.episodes}")
    candidates = _candidates(s.run, s.finals)
    out = Path(s.out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out} exists and is not empty; choose another --out")
    task = json.loads((s.run / "run.json").read_text())["task"]
    rates: dict[str, list[dict[str, float]]] = {c.label: [] for c in candidates}
    total = len(s.seeds) * len(candidates)
    for i, k in enumerate(s.seeds):
        for index, c in enumerate(candidates):
            if on_evaluation is not None:
                on_evaluation(i * len(candidates) + index, total, f"seed {k}: {c.label}")
            if c.checkpoint is None:
                name = f"offline_{'with' if c.twin_buffer else 'without'}_buffer_seed{k}"
                with tempfile.TemporaryDirectory() as scratch:  # the run's logs hold nothing
                    policy = _offline_policy(s.run, Path(scratch) / "run", k, c.twin_buffer)
                runner = TwinrlRunner(policy, name=name)
            else:
                runner = TwinrlRunner(c.checkpoint)
            report = evaluate(
                runner,
                task,
                world="plant",
                grid=s.grid,
                episodes=s.episodes,
                seed=EVAL_SEED + k,
                out=out / "evaluations" / f"seed{k}" / f"{index:02d}",
            )
            rates[c.label].append({r: report.success_rate().get(r, 0.0) for r in REGION_NAMES})
    per_region = {r: sum(c.episodes for c in report.cells if c.region == r) for r in REGION_NAMES}
    result = {
        "run": str(s.run),
        "task": task,
        "evaluation": {
            "grid": list(s.grid),
            "episodes_per_cell": s.episodes,
            "seeds": list(s.seeds),
            "plant_seed": f"{EVAL_SEED} + seed",
        },
        "policies": {
            label: {"per_seed": values, "mean": _mean(values), "stderr": _stderr(values)}
            for label, values in rates.items()
        },
        # None when Stage II kept no rollout (then there is no twin buffer to compare)
        "twin_buffer_offline_gain": (
            _paired_gain(rates[WITH_BUFFER], rates[WITHOUT_BUFFER])
            if WITH_BUFFER in rates
            else None
        ),
    }
    (out / "stages.json").write_text(json.dumps(result, indent=1))
    _plot(result, out / "stages.png")
    (out / "stages.md").write_text(_markdown(result, per_region))
    return result


def _mean(values: list[dict[str, float]]) -> dict[str, float]:
    return {r: float(np.mean([v[r] for v in values])) for r in REGION_NAMES}


def _stderr(values: list[dict[str, float]]) -> dict[str, float | None]:
    """Standard error of the mean over seeds (None with one seed)."""
    if len(values) < 2:
        return {r: None for r in REGION_NAMES}
    return {
        r: float(np.std([v[r] for v in values], ddof=1) / np.sqrt(len(values)))
        for r in REGION_NAMES
    }


def _paired_gain(with_: list[dict[str, float]], without: list[dict[str, float]]) -> dict:
    """The twin buffer's effect on the offline phase, paired by seed."""
    differences = [
        {r: a[r] - b[r] for r in REGION_NAMES} for a, b in zip(with_, without, strict=True)
    ]
    return {"mean": _mean(differences), "stderr": _stderr(differences)}


def _pct(value: float, stderr: float | None) -> str:
    return f"{100 * value:.0f} %" + ("" if stderr is None else f" ± {100 * stderr:.0f}")


def _markdown(result: dict, per_region: dict[str, int]) -> str:
    e = result["evaluation"]
    seeds = len(e["seeds"])
    counts = " / ".join(str(per_region[r]) for r in REGION_NAMES)
    totals = " / ".join(str(seeds * per_region[r]) for r in REGION_NAMES)
    lines = [
        f"# What each stage adds: {result['task']}",
        "",
        f"Run `{result['run']}`. Each policy: {seeds} evaluation(s) in the plant on a "
        f"{e['grid'][0]}x{e['grid'][1]} grid, {e['episodes_per_cell']} episode(s) per cell "
        f"({counts} in {' / '.join(REGION_NAMES)} each, {totals} in all), the same "
        "configurations for every policy. Mean over evaluations ± its standard error.",
        "",
        "| policy | ID | OOD |",
        "|---|---|---|",
    ]
    for label, p in result["policies"].items():
        lines.append(
            f"| {label} | {_pct(p['mean']['ID'], p['stderr']['ID'])} "
            f"| {_pct(p['mean']['OOD'], p['stderr']['OOD'])} |"
        )
    gain = result["twin_buffer_offline_gain"]
    lines.append("")
    if gain is None:
        lines.append("Stage II kept no rollout, so the run has no twin buffer to compare.")
    else:
        lines.append(
            "The twin buffer's effect on the offline phase (with minus without, paired by "
            f"seed): ID {_signed(gain['mean']['ID'], gain['stderr']['ID'])}, "
            f"OOD {_signed(gain['mean']['OOD'], gain['stderr']['OOD'])} points."
        )
    lines += ["", "![success of each policy](stages.png)", ""]
    return "\n".join(lines)


def _signed(value: float, stderr: float | None) -> str:
    return f"{100 * value:+.1f}" + ("" if stderr is None else f" ± {100 * stderr:.1f}")


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(result["policies"])
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(labels) + 1.4), dpi=120)
    y = np.arange(len(labels))
    for offset, region in zip((-0.18, 0.18), REGION_NAMES, strict=True):
        means = [result["policies"][label]["mean"][region] for label in labels]
        errors = [result["policies"][label]["stderr"][region] or 0.0 for label in labels]
        ax.barh(y + offset, means, height=0.36, xerr=errors, label=region, capsize=2)
    ax.set_yticks(y, labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 1)
    ax.set_xlabel("plant success (mean over evaluations, ± standard error)")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
