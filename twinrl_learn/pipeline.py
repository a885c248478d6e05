"""``twinrl demo``: the three TwinRL stages on a built-in cell with the plant as the
real robot, then the baselines on the same plant and seeds, and a report.

Stages (shared by every method and seed):

1. real demos: teleop-like expert demos in the plant, region ID only; twin demos
   (ID + OOD) synthesized by the planner; two SFT policies: real only (what the
   baselines start from) and real + twin (TwinRL's Stage I);
2. twin RL from the real + twin policy, imitating real and twin demos; its successful
   rollouts are the twin buffer;
3. failure mining in the twin with the Stage II policy: the first reset targets.

Then real RL in the plant for each method and seed (``RealRL``), all with the same
simulated operator and evaluation grid:

====================== ============= =========== =========== =========== ================
method                 starts from   imitates    twin buffer resets      objective
====================== ============= =========== =========== =========== ================
TwinRL                 Stage II      real + twin yes         mined+unif. beta L_IL+eta L_Q
TwinRL w/o twin buffer Stage II      real + twin no          mined+unif. beta L_IL+eta L_Q
ConRFT-style           real-only SFT real        no          uniform     beta L_IL+eta L_Q
HiL-SERL               real-only SFT (none)      no          uniform     SAC (no IL term)
====================== ============= =========== =========== =========== ================

"Imitates" is the demo buffer (interventions join it in every method; HiL-SERL keeps
it as RLPD's demo half but has no imitation term).

Outputs: ``report.md`` (curves, tables), ``report.json``, ``curves.png``, every
episode log (each stage's ``session/`` folders), ``catalog.parquet`` over all of them
and ``representative.rrd`` (a TwinRL episode with an intervention and its last one).
With ``resume`` a stopped pipeline continues: finished stages are skipped and an
interrupted real-RL run resumes from its last checkpoint. The real-RL runs are
independent (each has its own seed, folder and plant), so ``workers`` processes run
them side by side; the results do not depend on how many.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import queue
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from twinrl_data.catalog import build_index
from twinrl_data.cli import quiet_encoders
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_data.view import save_rrd
from twinrl_learn.evaluate import evaluate, grid_cells
from twinrl_learn.mining import mine
from twinrl_learn.real_rl import EvalPoint, RealRL, RealRLSettings, load_evaluations, minutes_to
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.settings import RLConfig, SFTConfig, check_inputs
from twinrl_learn.sft import train_sft
from twinrl_learn.stage1 import record_real_demos
from twinrl_learn.twin_rl import TwinRLSettings, run_twin_rl
from twinrl_robot.operator import OperatorRule
from twinrl_sim.expand import expand
from twinrl_sim.tasks import REGION_NAMES, make_task

Log = Callable[[str], None]


@dataclass(frozen=True)
class Preset:
    """The scale of a pipeline run."""

    policy: str  # state (privileged, fast) or vla (cameras + language)
    real_demos: int
    twin_id: int
    twin_ood: int
    twin_rl_steps: int
    twin_envs: int
    mining_grid: tuple[int, int]
    mining_episodes: int
    plant_steps: int  # per real-RL run (10 Hz: 600 = 1 plant minute)
    eval_every: int
    eval_grid: tuple[int, int]
    eval_episodes: int
    offline_steps: int
    refresh_every: int
    seeds: tuple[int, ...]
    sft_steps: int | None = None  # None: the SFT defaults of the policy kind
    inputs: str = "absolute"  # the state policy's inputs (twinrl_learn.policy)


PRESETS = {
    # A few minutes: checks that every stage runs (no learning to speak of).
    "smoke": Preset(
        policy="state",
        real_demos=2,
        twin_id=2,
        twin_ood=2,
        twin_rl_steps=40,
        twin_envs=2,
        mining_grid=(2, 2),
        mining_episodes=1,
        plant_steps=100,
        eval_every=50,
        eval_grid=(2, 2),
        eval_episodes=1,
        offline_steps=5,
        refresh_every=1,
        seeds=(0,),
        sft_steps=30,
    ),
    "quick": Preset(
        policy="state",
        # Objects seen from the TCP: measured better at every stage than absolute poses.
        inputs="relative",
        real_demos=30,
        # 105 + 105 twin demos: SFT on them reached 61 / 70 % (ID / OOD) in the plant
        # against 41 / 56 % with 30 + 30; synthesized without cameras, they fit the time.
        twin_id=105,
        twin_ood=105,
        # Twin RL is where RL is cheap: from the same SFT policy (44 / 44 % ID / OOD in
        # the plant, 64 episodes per region), 1600 twin steps reached 61 / 75 % and 9600
        # (4 min) 75 / 91 %.
        twin_rl_steps=9600,
        twin_envs=8,
        mining_grid=(4, 4),
        mining_episodes=2,
        plant_steps=2400,
        # 32 episodes per region per evaluation, each at its own configuration (95 %
        # takes 31 of 32): with 16 (4x4, 2 each) the final TwinRL policies of a run
        # measured 88-94 % in each region, and 94-98 % over 64 (8x8, 2 each). Every 2
        # plant minutes keeps the preset under 20 minutes.
        eval_every=1200,
        eval_grid=(8, 8),
        eval_episodes=1,
        offline_steps=200,
        refresh_every=8,
        seeds=(0, 1, 2),
    ),
    "paper": Preset(
        policy="vla",
        real_demos=30,
        twin_id=60,
        twin_ood=30,
        twin_rl_steps=20000,
        twin_envs=8,
        mining_grid=(8, 8),
        mining_episodes=2,
        plant_steps=18000,
        eval_every=1200,
        eval_grid=(8, 8),  # 32 episodes per region, as in quick
        eval_episodes=1,
        offline_steps=1000,
        refresh_every=10,
        seeds=(0, 1, 2),
    ),
}


@dataclass(frozen=True)
class Method:
    """How one compared method runs real RL."""

    name: str
    slug: str
    rl_method: str
    from_twin: bool  # start from Stage II (else from the real-only SFT policy)
    twin_buffer: bool
    mined_resets: bool


METHOD_TABLE = (
    Method("TwinRL", "twinrl", "twinrl", True, True, True),
    Method("TwinRL w/o twin buffer", "twinrl_no_buffer", "twinrl", True, False, True),
    Method("ConRFT-style", "conrft", "conrft", False, False, False),
    Method("HiL-SERL", "hil_serl", "hil-serl", False, False, False),
)


def twin_rl_config(p: Preset) -> RLConfig:
    """The RL settings of a preset's Stage II."""
    return RLConfig.for_method("twinrl", offline_steps=p.offline_steps)


def real_rl_config(method: Method, p: Preset, seed: int) -> RLConfig:
    """The RL settings of one real-RL run: the method's, with the preset's offline phase
    (HiL-SERL has none: RLConfig.for_method)."""
    offline = {} if method.rl_method == "hil-serl" else {"offline_steps": p.offline_steps}
    return RLConfig.for_method(method.rl_method, seed=seed, **offline)


def run_demo(
    task: str = "pick_place",
    preset: str | Preset = "quick",
    out: str | Path = "out/twinrl_demo",
    *,
    seeds: tuple[int, ...] | None = None,
    inputs: str | None = None,
    workers: int = 2,
    resume: bool = False,
    log: Log = print,
    on_progress: Callable[[RunProgress], None] | None = None,
) -> dict[str, Any]:
    """Run the pipeline and write the report; returns ``report.json``'s content.
    ``preset`` is a name of :data:`PRESETS` or a :class:`Preset` of one's own (e.g.
    ``replace(PRESETS["quick"], twin_id=30)``; its report calls it ``custom``).
    ``inputs`` overrides the preset's state-policy inputs (``absolute``/``relative``);
    ``on_progress`` hears from every real-RL run after each of its episodes."""
    make_task(task)
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    if isinstance(preset, Preset):
        p, preset = preset, "custom"
    elif preset in PRESETS:
        p = PRESETS[preset]
    else:
        raise ValueError(f"--preset must be one of {', '.join(PRESETS)}, got '{preset}'")
    if inputs is not None:
        check_inputs(inputs, p.policy)
        p = replace(p, inputs=inputs)
    seeds = tuple(seeds) if seeds else p.seeds
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not resume:
        raise ValueError(f"{out} exists and is not empty; pass --resume or choose another --out")
    recorded = {"task": task, "preset": preset, "inputs": p.inputs}
    if preset == "custom":  # a custom run resumes only with the very same scale
        recorded["settings"] = json.loads(json.dumps(asdict(p)))
    _check_same_run(out / "run.json", recorded)
    out.mkdir(parents=True, exist_ok=True)
    stage1 = _stage1(task, p, out / "stage1", log)
    stage2 = _stage2(task, p, out, stage1, log)
    targets = _mining(task, p, out, stage2, log)
    runs: dict[str, dict[int, Path]] = {}
    jobs = []
    for method in METHOD_TABLE:
        for seed in seeds:
            folder = out / "real_rl" / method.slug / f"seed{seed}"
            runs.setdefault(method.name, {})[seed] = folder
            jobs.append(RealRLJob(task, p, method, seed, folder, stage1, stage2, targets))
    _run_jobs(jobs, workers, log, on_progress)
    log("writing the report")
    return write_report(task, preset, p, out, stage1, runs, seeds)


def _check_same_run(path: Path, settings: dict[str, Any]) -> None:
    """Record what a run is; a resumed run must be the same one (nothing mixed)."""
    if path.is_file():
        recorded = json.loads(path.read_text())
        for key, value in settings.items():
            if recorded.get(key) != value:
                raise ValueError(
                    f"--resume: {path.parent} is a run with {key} {recorded.get(key)!r}, "
                    f"not {value!r}; resume it with the same options or choose another --out"
                )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=1))


# ------------------------------------------------------------------ stages
def _done(folder: Path) -> bool:
    return (folder / ".done").is_file()


def _mark_done(folder: Path) -> None:
    (folder / ".done").write_text("")


def _fresh(folder: Path) -> Path:
    """A stage folder to (re)start: whatever an interrupted attempt left is removed."""
    if folder.exists():
        shutil.rmtree(folder)
    return folder


def stage1_paths(folder: Path, policy: str) -> dict[str, Path]:
    """Where Stage I keeps its data and policies in a run's ``stage1`` folder."""
    return {
        "real": folder / "real",
        "twin": folder / "twin" / "dataset",
        "sft_real": folder / f"{policy}_real",
        "sft_twin": folder / f"{policy}_real_twin",
    }


def run_preset(out: Path) -> Preset:
    """The preset a run in ``out`` was made with (its ``run.json``)."""
    path = Path(out) / "run.json"
    if not path.is_file():
        raise ValueError(f"{out} is not a `twinrl demo` run folder (no run.json)")
    recorded = json.loads(path.read_text())
    if "settings" in recorded:  # a custom preset
        fields = recorded["settings"]
        return Preset(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
    if recorded["preset"] not in PRESETS:
        raise ValueError(
            f"{out} was made with preset '{recorded['preset']}', which this version lacks"
        )
    return replace(PRESETS[recorded["preset"]], inputs=recorded["inputs"])


def _stage1(task: str, p: Preset, folder: Path, log: Log) -> dict[str, Path]:
    paths = stage1_paths(folder, p.policy)
    if _done(folder):
        return paths
    _fresh(folder).mkdir(parents=True)
    log(f"Stage I: recording {p.real_demos} teleop-like demos in the plant (ID)")
    kept, recorded = record_real_demos(task, p.real_demos, folder)
    log(f"Stage I: kept {kept} of {recorded}; synthesizing {p.twin_id} ID + {p.twin_ood} OOD")
    expand(
        task,
        id_count=p.twin_id,
        ood_count=p.twin_ood,
        out=folder / "twin",
        seed=1,
        images=p.policy == "vla",  # a state policy never reads them
    )
    for name, datasets in (
        ("sft_real", [paths["real"]]),
        ("sft_twin", [paths["real"], paths["twin"]]),
    ):
        log(f"Stage I: SFT {paths[name].name}")
        train_sft(
            SFTConfig(
                datasets=[str(d) for d in datasets],
                out=str(paths[name]),
                policy=p.policy,
                steps=p.sft_steps,
                inputs=p.inputs,
            )
        )
        _plant_eval(paths[name], task, p, _eval_folder(paths[name]))
    _mark_done(folder)
    return paths


def _eval_folder(checkpoint: Path) -> Path:
    """Where a Stage I policy's plant evaluation lies: beside it."""
    return checkpoint.with_name(f"{checkpoint.name}_eval")


def _plant_eval(checkpoint: Path, task: str, p: Preset, out: Path) -> None:
    """A starting policy's success in the plant, on the real-RL runs' evaluation grid."""
    evaluate(
        TwinrlRunner(checkpoint),
        task,
        world="plant",
        grid=p.eval_grid,
        episodes=p.eval_episodes,
        seed=10_000,
        out=_fresh(out),
    )


def _demos(stage1: dict[str, Path], *, twin: bool) -> list[str]:
    """The imitation data of a run: the real demos, plus the twin demos for a policy
    that was fine-tuned on them (imitating only the ID real demos, the quick preset's
    twin RL wore its OOD success down from 50 to 0 %, 32 plant episodes per region)."""
    return [str(stage1["real"])] + ([str(stage1["twin"])] if twin else [])


def _stage2(task: str, p: Preset, out: Path, stage1: dict[str, Path], log: Log) -> Path:
    folder = out / "stage2"
    if not _done(folder):
        log(f"Stage II: twin RL, {p.twin_envs} envs, {p.twin_rl_steps} steps")
        run_twin_rl(
            TwinRLSettings(
                task=task,
                init=str(stage1["sft_twin"]),
                out=str(_fresh(folder)),
                demos=_demos(stage1, twin=True),
                envs=p.twin_envs,
                steps=p.twin_rl_steps,
                rl=twin_rl_config(p),
            )
        )
        _mark_done(folder)
    if not (folder / "plant_eval" / "eval.json").is_file():  # also for runs made before it
        log("Stage II: evaluating the twin-RL policy in the plant")
        _plant_eval(folder / "agent", task, p, folder / "plant_eval")
    return folder


def _mining(task: str, p: Preset, out: Path, stage2: Path, log: Log) -> Path:
    path = out / "targets.json"
    if not path.is_file():
        log("Stage III: mining failure-prone configurations in the twin")
        _fresh(out / "targets")
        mine(
            TwinrlRunner(stage2 / "agent", name="stage2"),
            task,
            out=path,
            grid=p.mining_grid,
            episodes=p.mining_episodes,
        )
    return path


@dataclass(frozen=True)
class RunProgress:
    """Where one real-RL run stands after an episode (sent from its worker process)."""

    method: str
    seed: int
    plant_steps: int
    success_rate: dict[str, float]  # of its latest evaluation


@dataclass(frozen=True)
class RealRLJob:
    """One method and seed of real RL: everything a worker process needs."""

    task: str
    p: Preset
    method: Method
    seed: int
    folder: Path
    stage1: dict[str, Path]
    stage2: Path
    targets: Path


def _run_jobs(
    jobs: list[RealRLJob],
    workers: int,
    log: Log,
    on_progress: Callable[[RunProgress], None] | None,
) -> None:
    """Run the jobs, ``workers`` at a time in spawned processes (1: in this one), passing
    their log lines and progress on to ``log`` and ``on_progress`` as they come."""
    pending = [job for job in jobs if not _done(job.folder)]
    if workers == 1 or len(pending) <= 1:
        for job in pending:
            _real_rl(job, log, on_progress or (lambda _: None))
        return
    context = multiprocessing.get_context("spawn")
    messages = context.Queue()
    with ProcessPoolExecutor(
        min(workers, len(pending)),
        mp_context=context,
        initializer=_start_worker,
        initargs=(messages,),
    ) as pool:
        futures = [pool.submit(_real_rl_in_worker, job) for job in pending]
        while not all(f.done() for f in futures) or not messages.empty():
            if any(f.done() and f.exception() is not None for f in futures):
                pool.shutdown(wait=False, cancel_futures=True)  # runs under way finish
                break
            try:
                message = messages.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(message, RunProgress):
                if on_progress is not None:
                    on_progress(message)
            else:
                log(message)
        for future in futures:
            future.result()  # a worker's error is raised here, as if run in this process


_worker_messages = None


def _start_worker(messages) -> None:
    global _worker_messages
    _worker_messages = messages
    torch.set_num_threads(1)
    quiet_encoders()


def _real_rl_in_worker(job: RealRLJob) -> None:
    _real_rl(job, _worker_messages.put, _worker_messages.put)


def real_rl_settings(job: RealRLJob) -> RealRLSettings:
    """The settings of one method's real-RL run."""
    task, p, method, seed, folder = job.task, job.p, job.method, job.seed, job.folder
    stage1, stage2, targets = job.stage1, job.stage2, job.targets
    twin_buffer = stage2 / "twin_buffer"
    return RealRLSettings(
        task=task,
        init=str(stage2 / "agent" if method.from_twin else stage1["sft_real"]),
        out=str(folder),
        demos=_demos(stage1, twin=method.from_twin),
        twin_buffer=str(twin_buffer) if method.twin_buffer and twin_buffer.exists() else None,
        targets=str(targets) if method.mined_resets else None,
        refresh_every=p.refresh_every if method.mined_resets else 0,
        mining_grid=p.mining_grid,
        mining_episodes=1,
        plant_steps=p.plant_steps,
        eval_every=p.eval_every,
        eval_grid=p.eval_grid,
        eval_episodes=p.eval_episodes,
        operator=OperatorRule(),
        rl=real_rl_config(method, p, seed),
    )


def _real_rl(job: RealRLJob, log: Log, on_progress: Callable[[RunProgress], None]) -> None:
    """Start or resume one unfinished run (``_run_jobs`` skips the finished ones)."""
    method, seed, folder = job.method, job.seed, job.folder
    settings = real_rl_settings(job)
    if (folder / "run.json").is_file():
        log(f"real RL: {method.name}, seed {seed}: resuming")
        real = RealRL.resume(settings)
    else:
        log(f"real RL: {method.name}, seed {seed}")
        folder.parent.mkdir(parents=True, exist_ok=True)
        _fresh(folder)  # what an attempt stopped before its first checkpoint left
        real = RealRL.start(settings)

    def report(record, real: RealRL) -> None:
        rates = real.evaluations[-1].success_rate if real.evaluations else {}
        on_progress(RunProgress(method.name, seed, real.run_state.agent.env_steps, rates))

    real.run(on_episode=report)
    _mark_done(folder)


# ------------------------------------------------------------------ report
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
            }
        )
    return {
        "plant_minutes_to_95": {r: _median([s["to95"][r] for s in per_seed]) for r in REGION_NAMES},
        "final_success": {
            r: float(np.median([s["final"].get(r, 0.0) for s in per_seed])) for r in REGION_NAMES
        },
        "interventions": int(np.median([s["interventions"] for s in per_seed])),
        "plant_steps": int(np.median([s["plant_steps"] for s in per_seed])),
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
        cells = [
            " / ".join(_pct(e.success_rate.get(r, 0.0)) for r in REGION_NAMES) for e in evaluations
        ]
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
            _eval_folder(stage1["sft_real"]),
        ),
        (
            "sft_real_twin",
            f"Stage I: SFT on {twin_data}",
            _eval_folder(stage1["sft_twin"]),
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
    (out / "report.json").write_text(json.dumps(report, indent=1))
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
        "| intervention steps | robot steps |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in methods.items():
        lines.append(
            f"| {name} | {_fmt_minutes(m['plant_minutes_to_95']['ID'])} "
            f"| {_fmt_minutes(m['plant_minutes_to_95']['OOD'])} "
            f"| {100 * m['final_success']['ID']:.0f} % | {100 * m['final_success']['OOD']:.0f} % "
            f"| {m['interventions']} | {m['plant_steps']} |"
        )
    lines += [
        "",
        "Each run's evaluations, ID / OOD (an evaluation follows the episode that "
        "crosses its step count, so the minutes differ a little between runs):",
        "",
    ]
    lines += _per_seed_table(runs)
    lines += [
        "",
        "Per run: `real_rl/<method>/seed<k>/` (curve.png, evaluations/, session/, "
        "resets-*.rrd). All episodes are indexed in `catalog.parquet`; "
        "`representative.rrd` shows a TwinRL episode with an operator takeover and its "
        "last training episode.",
        "",
        "Settings: " + json.dumps(asdict(p)),
    ]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    build_index([out], out / "catalog.parquet")
    _representative(runs[METHOD_TABLE[0].name], out / "representative.rrd")
    return report


def _representative(folders: dict[int, Path], path: Path) -> None:
    session = Session(next(iter(folders.values())) / "session")
    entries, paths = session.entries, session.episode_paths()
    helped = [p for p, e in zip(paths, entries, strict=True) if e.get("num_interventions")]
    chosen = ([helped[-1]] if helped else []) + [paths[-1]]
    save_rrd([read_episode(p) for p in dict.fromkeys(chosen)], path, force=True)
