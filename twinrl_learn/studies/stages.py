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

Each evaluation (one policy, one seed, its offline phase included) is a job of its own,
on ``workers`` worker processes or Ray tasks where ``cluster`` says
(:func:`~twinrl_data.executor.make_executor`); each is seeded alone, so the study comes
out the same wherever they run.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_data.executor import InlineExecutor, Send, spreading_executor
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate, single_threaded
from twinrl_learn.policy import Policy
from twinrl_learn.real_rl import RealRL
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.studies.layout import stage1_paths
from twinrl_learn.studies.pipeline import RealRLJob, real_rl_settings, run_preset
from twinrl_learn.studies.presets import METHOD_TABLE, Method
from twinrl_learn.studies.settings import StagesSettings
from twinrl_sim.tasks import REGION_NAMES

EVAL_SEED = 20_000  # apart from the pipeline's own evaluations (10_000 + ...)
WITH_BUFFER = "Stage II + offline phase, with the twin buffer"
WITHOUT_BUFFER = "Stage II + offline phase, without the twin buffer"
TWIN_RL_METHODS = [m for m in METHOD_TABLE if m.from_twin]  # with and without the buffer


@dataclass(frozen=True)
class _Candidate:
    label: str
    checkpoint: Path | None  # None: made per seed by the offline phase of ``method``
    method: Method | None = None


def _candidates(run: Path, finals: bool) -> list[_Candidate]:
    """The run's policies to measure, checked to exist (a clear error if not)."""
    stage1 = stage1_paths(run / "stage1", run_preset(run).policy)
    stage2 = run / "stage2"
    if not stage1["sft_twin"].is_dir() or not (stage2 / ".done").is_file():
        raise LearnError(
            f"{run} has not finished Stage II; resume its pipeline first (twinrl demo, `resume`)"
        )
    with_buffer = next(m for m in TWIN_RL_METHODS if m.twin_buffer)
    without_buffer = next(m for m in TWIN_RL_METHODS if not m.twin_buffer)
    candidates = [
        _Candidate("Stage I: SFT, real demos only", stage1["sft_real"]),
        _Candidate("Stage I: SFT, real + twin demos", stage1["sft_twin"]),
        _Candidate("Stage II: twin RL", stage2 / "agent"),
    ]
    if (stage2 / "twin_buffer").exists():  # as the pipeline: Stage II kept a rollout
        candidates.append(_Candidate(WITH_BUFFER, None, with_buffer))
    candidates.append(_Candidate(WITHOUT_BUFFER, None, without_buffer))
    if finals:
        for method in TWIN_RL_METHODS:
            for folder in sorted((run / "real_rl" / method.slug).glob("seed*")):
                if (folder / ".done").is_file():
                    label = f"{method.name}, {folder.name} final"
                    candidates.append(_Candidate(label, folder / "agent"))
    return candidates


def _offline_policy(run: Path, out: Path, seed: int, method: Method) -> Policy:
    """The Stage II policy after the offline phase of ``method``'s real-RL run with
    ``seed``, with the pipeline's very settings for that run."""
    p = run_preset(run)
    task = json.loads((run / "run.json").read_text())["task"]
    stage1 = stage1_paths(run / "stage1", p.policy)
    job = RealRLJob(task, p, method, seed, out, stage1, run / "stage2", run / "targets.json")
    # Resets and targets play no part before the first robot step.
    settings = replace(real_rl_settings(job), targets=None, refresh_every=0, show_resets=False)
    real = RealRL.start(settings)
    try:
        real.run_state.pretrain()
    finally:
        real.close()
    return real.run_state.agent.policy


def measure_stages(
    settings: StagesSettings,
    on_evaluation: Callable[[int, int, str], None] | None = None,
) -> dict[str, object]:
    """Measure every candidate policy of ``settings.run``; write ``stages.json``,
    ``stages.md`` and ``stages.png`` to ``settings.out``; return the JSON's content.
    ``on_evaluation(done, total, label)`` hears before each evaluation."""
    s = settings
    if not s.seeds:
        raise SettingError("seeds", "needs at least one seed")
    if s.episodes < 1:
        raise SettingError("episodes", f"must be at least 1, got {s.episodes}")
    candidates = _candidates(s.run, s.finals)
    out = Path(s.out)
    if out.exists() and any(out.iterdir()):
        raise LearnError(f"{out} exists and is not empty; choose another output folder")
    task = json.loads((s.run / "run.json").read_text())["task"]
    jobs = [
        _Evaluation(s.run, out / "evaluations" / f"seed{k}" / f"{index:02d}", task, k, c, s)
        for k in s.seeds
        for index, c in enumerate(candidates)
    ]
    started = 0

    def starting(label: str) -> None:
        nonlocal started
        if on_evaluation is not None:
            on_evaluation(started, len(jobs), label)
        started += 1

    spread = spreading_executor(s.workers, s.cluster, initializer=single_threaded)
    with spread or InlineExecutor() as executor:
        measured = executor.run(_evaluated, jobs, starting)
    rates: dict[str, list[dict[str, float]]] = {c.label: [] for c in candidates}
    for job, (rate, _) in zip(jobs, measured, strict=True):
        rates[job.candidate.label].append(rate)
    per_region = measured[-1][1]  # episodes per region of one evaluation (all alike)
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
    write_text_atomic(out / "stages.json", json.dumps(result, indent=1))
    _plot(result, out / "stages.png")
    write_text_atomic(out / "stages.md", _markdown(result, per_region))
    return result


@dataclass(frozen=True)
class _Evaluation:
    """One policy measured with one seed: a job that runs anywhere."""

    run: Path
    out: Path
    task: str
    seed: int
    candidate: _Candidate
    settings: StagesSettings


def _evaluated(job: _Evaluation, send: Send) -> tuple[dict[str, float], dict[str, int]]:
    """``job``'s success rate per region and its episodes per region."""
    c, k, s = job.candidate, job.seed, job.settings
    send(f"seed {k}: {c.label}")
    if c.checkpoint is None:
        with tempfile.TemporaryDirectory() as scratch:  # the run's logs hold nothing
            policy = _offline_policy(job.run, Path(scratch) / "run", k, c.method)
        runner = TwinrlRunner(policy, name=f"offline:{c.method.slug}:seed{k}")
    else:
        runner = TwinrlRunner(c.checkpoint)
    report = evaluate(
        runner,
        job.task,
        world="plant",
        grid=s.grid,
        episodes=s.episodes,
        seed=EVAL_SEED + k,
        out=job.out,
    )
    rates = {r: report.success_rate().get(r, 0.0) for r in REGION_NAMES}
    return rates, {r: sum(c.episodes for c in report.cells if c.region == r) for r in REGION_NAMES}


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
