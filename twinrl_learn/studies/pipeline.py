"""``twinrl demo``: the three TwinRL stages on a built-in cell with the plant as the
real robot, then the baselines on the same plant and seeds, and a report.

Stages (shared by every method and seed):

1. real demos: teleop-like expert demos in the plant, region ID only; twin demos
   (ID + OOD) synthesized by the planner; two SFT policies: real only (what the
   baselines start from) and real + twin (TwinRL's Stage I);
2. twin RL from the real + twin policy, imitating real and twin demos; its successful
   rollouts are the twin buffer; where a classifier judges success (``quick-vision``),
   it is trained again on Stage I's twin episodes plus all these rollouts, the
   policy's own successes and failures, labelled by the twin;
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
it as RLPD's demo half but has no imitation term; its offline phase warms the critic
alone, as its authors' recipe has it: ``RLConfig.for_method``).

Outputs: ``report.md`` (curves, tables), ``report.json``, ``curves.png``, every
episode log (each stage's ``session/`` folders), ``catalog.parquet`` over all of them
and ``representative.rrd`` (a TwinRL episode with an intervention and its last one).
With ``resume`` a stopped pipeline continues: finished stages are skipped and an
interrupted real-RL run resumes from its last checkpoint. The real-RL runs are
independent (each has its own seed, folder and plant), so ``workers`` processes run
them side by side, or Ray tasks on a cluster (``cluster``); on a cluster, Stage I's
synthesis, Stage II's twin environments and the mining's grid spread over it too. The
results do not depend on how many workers or machines.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch

from twinrl_data.atomic import write_text_atomic
from twinrl_data.console import quiet_encoders
from twinrl_data.errors import SettingError
from twinrl_data.executor import cluster_address, make_executor
from twinrl_learn.compute import check_device
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate
from twinrl_learn.mining import mine
from twinrl_learn.real_rl import RealRL, RealRLSettings
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.settings import SFTConfig, check_inputs
from twinrl_learn.sft import train_sft
from twinrl_learn.studies.layout import eval_folder, stage1_paths
from twinrl_learn.studies.presets import (
    METHOD_TABLE,
    PRESETS,
    Method,
    Preset,
    real_rl_config,
    twin_rl_config,
)
from twinrl_learn.studies.report import write_report
from twinrl_learn.studies.table1 import (
    fit_look,
    fit_twin_classifier,
    record_real_demos,
    train_task_estimator,
    train_twin_classifier,
)
from twinrl_learn.twin_rl import TwinRLSettings, run_twin_rl
from twinrl_robot.operator import OperatorRule
from twinrl_sim.expand import expand
from twinrl_sim.tasks import make_task

Log = Callable[[str], None]


def run_demo(
    task: str = "pick_place",
    preset: str | Preset = "quick",
    out: str | Path = "out/twinrl_demo",
    *,
    seeds: tuple[int, ...] | None = None,
    inputs: str | None = None,
    workers: int = 2,
    resume: bool = False,
    device: str = "auto",
    log: Log = print,
    on_progress: Callable[[RunProgress], None] | None = None,
    cluster: str = "",
) -> dict[str, Any]:
    """Run the pipeline and write the report; returns ``report.json``'s content.
    ``preset`` is a name of :data:`PRESETS` or a :class:`Preset` of one's own (e.g.
    ``replace(PRESETS["quick"], twin_id=30)``; its report calls it ``custom``).
    ``inputs`` overrides the preset's state-policy inputs (``absolute``/``relative``);
    ``on_progress`` hears from every real-RL run after each of its episodes; ``device``
    is where every stage's networks run (:mod:`twinrl_learn.compute`); ``cluster`` where
    the twin demos, Stage II's environments, the mining and the real-RL runs do
    (:func:`twinrl_data.executor.cluster_address`: ``out`` on storage every node sees)."""
    make_task(task)
    check_device(device)
    cluster_address(cluster)
    if workers < 1:
        raise SettingError("workers", f"must be at least 1, got {workers}")
    if isinstance(preset, Preset):
        p, preset = preset, "custom"
    elif preset in PRESETS:
        p = PRESETS[preset]
    else:
        raise SettingError("preset", f"must be one of {', '.join(PRESETS)}, got '{preset}'")
    if inputs is not None:
        check_inputs(inputs, p.policy)
        p = replace(p, inputs=inputs)
    seeds = tuple(seeds) if seeds else p.seeds
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not resume:
        raise LearnError(
            f"{out} exists and is not empty; resume the run in it or choose another folder"
        )
    recorded = {"task": task, "preset": preset, "inputs": p.inputs}
    if preset == "custom":  # a custom run resumes only with the very same scale
        recorded["settings"] = json.loads(json.dumps(asdict(p)))
    _check_same_run(out / "run.json", recorded)
    out.mkdir(parents=True, exist_ok=True)
    stage1 = _stage1(task, p, out / "stage1", log, device, cluster)
    stage2 = _stage2(task, p, out, stage1, log, device, cluster)
    targets = _mining(task, p, out, stage2, _look(p, stage1), log, device, cluster)
    runs: dict[str, dict[int, Path]] = {}
    jobs = []
    for method in METHOD_TABLE:
        for seed in seeds:
            folder = out / "real_rl" / method.slug / f"seed{seed}"
            runs.setdefault(method.name, {})[seed] = folder
            jobs.append(RealRLJob(task, p, method, seed, folder, stage1, stage2, targets, device))
    _run_jobs(jobs, workers, log, on_progress, cluster)
    log("writing the report")
    return write_report(task, preset, p, out, stage1, runs, seeds)


def _check_same_run(path: Path, settings: dict[str, Any]) -> None:
    """Record what a run is; a resumed run must be the same one (nothing mixed)."""
    if path.is_file():
        recorded = json.loads(path.read_text())
        for key, value in settings.items():
            if recorded.get(key) != value:
                raise LearnError(
                    f"cannot resume {path.parent}: it is a run with `{key}` {recorded.get(key)!r}, "
                    f"not {value!r}; resume it with the same settings or choose another folder"
                )
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(settings, indent=1))


# ------------------------------------------------------------------ stages
def _done(folder: Path) -> bool:
    return (folder / ".done").is_file()


def _mark_done(folder: Path) -> None:
    write_text_atomic(folder / ".done", "")


def _fresh(folder: Path) -> Path:
    """A stage folder to (re)start: whatever an interrupted attempt left is removed."""
    if folder.exists():
        shutil.rmtree(folder)
    return folder


def run_preset(out: Path) -> Preset:
    """The preset a run in ``out`` was made with (its ``run.json``)."""
    path = Path(out) / "run.json"
    if not path.is_file():
        raise LearnError(f"{out} is not a `twinrl demo` run folder (no run.json)")
    recorded = json.loads(path.read_text())
    if "settings" in recorded:  # a custom preset
        fields = recorded["settings"]
        return Preset(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
    if recorded["preset"] not in PRESETS:
        raise LearnError(
            f"{out} was made with preset '{recorded['preset']}', which this version lacks"
        )
    return replace(PRESETS[recorded["preset"]], inputs=recorded["inputs"])


def _stage1(
    task: str, p: Preset, folder: Path, log: Log, device: str, cluster: str
) -> dict[str, Path]:
    paths = stage1_paths(folder, p.policy)
    if _done(folder):
        return paths
    _fresh(folder).mkdir(parents=True)
    log(f"Stage I: recording {p.real_demos} teleop-like demos in the plant (ID)")
    kept, recorded = record_real_demos(task, p.real_demos, folder)
    scene = None
    if p.fit_look:
        scene = fit_look(task, paths["real"], paths["look"])
        log(f"Stage I: the twin's look fitted to the real demos: {scene.effects['appearance']}")
    log(f"Stage I: kept {kept} of {recorded}; synthesizing {p.twin_id} ID + {p.twin_ood} OOD")
    expand(
        task,
        id_count=p.twin_id,
        ood_count=p.twin_ood,
        out=folder / "twin",
        seed=1,
        scene=scene,
        images=p.policy == "vla",  # a state policy never reads them
        cluster=cluster,
    )
    if p.perception:
        log(f"Stage I: a pose estimator from {p.perception} twin episodes per region")
        train_task_estimator(task, folder, scene, p.perception, seed=0, device=device)
    if p.classifier_episodes:
        log(f"Stage I: a success classifier from {p.classifier_episodes} twin episodes per region")
        train_twin_classifier(task, folder, scene, p.classifier_episodes, seed=0, device=device)
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
                perception=str(paths["estimator"]) if p.perception else None,
                device=device,
            )
        )
        _plant_eval(paths[name], task, p, eval_folder(paths[name]), device)
    _mark_done(folder)
    return paths


def _plant_eval(checkpoint: Path, task: str, p: Preset, out: Path, device: str) -> None:
    """A starting policy's success in the plant, on the real-RL runs' evaluation grid."""
    evaluate(
        TwinrlRunner(checkpoint, device=device),
        task,
        world="plant",
        grid=p.eval_grid,
        episodes=p.eval_episodes,
        seed=10_000,
        out=_fresh(out),
    )


def _look(p: Preset, stage1: dict[str, Path]) -> str | None:
    """The twin that Stage II and the mining run in: the fitted look, where the preset
    fits one (the look its image policy's twin data were made in)."""
    return str(stage1["look"]) if p.fit_look else None


def _demos(stage1: dict[str, Path], *, twin: bool) -> list[str]:
    """The imitation data of a run: the real demos, plus the twin demos for a policy
    that was fine-tuned on them (imitating only the ID real demos, the quick preset's
    twin RL wore its OOD success down from 50 to 0 %, 32 plant episodes per region)."""
    return [str(stage1["real"])] + ([str(stage1["twin"])] if twin else [])


def _stage2(
    task: str, p: Preset, out: Path, stage1: dict[str, Path], log: Log, device: str, cluster: str
) -> Path:
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
                twin=_look(p, stage1),
                device=device,
                cluster=cluster,  # none: the envs in this process
                rl=twin_rl_config(p),
            )
        )
        _mark_done(folder)
    if not (folder / "plant_eval" / "eval.json").is_file():  # also for runs made before it
        log("Stage II: evaluating the twin-RL policy in the plant")
        _plant_eval(folder / "agent", task, p, folder / "plant_eval", device)
    classifier = stage2_classifier(folder)
    if p.classifier_episodes and not (classifier / "metrics.json").is_file():
        # The scripted episodes' near misses are not the policy's failures: its own twin
        # rollouts, labelled by the twin, cut the false successes on its plant episodes
        # from 40 to 28 % (docs/results/pipeline-quick.md).
        log("Stage II: the success classifier again, with the twin-RL rollouts")
        shutil.rmtree(classifier, ignore_errors=True)  # one stopped before it was written
        fit_twin_classifier(
            [stage1["classifier_episodes"], folder / "session"], classifier, seed=0, device=device
        )
    return folder


def stage2_classifier(stage2: Path) -> Path:
    """The success classifier real RL judges by: Stage I's, trained again with Stage II's
    rollouts."""
    return stage2 / "success_classifier"


def _mining(
    task: str,
    p: Preset,
    out: Path,
    stage2: Path,
    twin: str | None,
    log: Log,
    device: str,
    cluster: str,
) -> Path:
    path = out / "targets.json"
    if not path.is_file():
        log("Stage III: mining failure-prone configurations in the twin")
        _fresh(out / "targets")
        mine(
            TwinrlRunner(stage2 / "agent", name="stage2", device=device),
            task,
            out=path,
            grid=p.mining_grid,
            episodes=p.mining_episodes,
            workers=None if cluster_address(cluster) is not None else 1,  # a cluster's CPUs
            twin=twin,
            cluster=cluster,
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
    device: str = "auto"


def _run_jobs(
    jobs: list[RealRLJob],
    workers: int,
    log: Log,
    on_progress: Callable[[RunProgress], None] | None,
    cluster: str,
) -> None:
    """Run the jobs, ``workers`` at a time (1: in this process) where ``cluster`` says,
    passing their log lines and progress on to ``log`` and ``on_progress`` as they come."""
    pending = [job for job in jobs if not _done(job.folder)]
    if not pending:
        return

    def dispatch(message: str | RunProgress) -> None:
        if isinstance(message, RunProgress):
            if on_progress is not None:
                on_progress(message)
        else:
            log(message)

    workers = min(workers, len(pending))
    with make_executor(workers, initializer=_start_worker, cluster=cluster) as executor:
        executor.run(_real_rl_job, pending, on_message=dispatch)


def _start_worker() -> None:
    torch.set_num_threads(1)
    quiet_encoders()


def _real_rl_job(job: RealRLJob, send: Callable[[str | RunProgress], None]) -> None:
    _real_rl(job, send, send)


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
        twin=_look(p, stage1),
        operator=OperatorRule(),
        operator_sees=str(stage1["estimator"]) if p.operator_sees else None,
        success="classifier" if p.classifier_episodes else "truth",
        classifier=str(stage2_classifier(stage2)) if p.classifier_episodes else None,
        success_frames=p.success_frames,
        device=job.device,
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
