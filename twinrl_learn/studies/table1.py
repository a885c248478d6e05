"""TwinRL's motivating experiment and Table I, reproduced with the plant as the real cell.

For each task:

1. "Real" demonstrations: ``real`` episodes recorded in the plant (hidden effects on)
   by the scripted expert acting as a teleoperator with human-like noise, region ID
   (the paper's region A) only; like an operator's dataset, only successful ones are
   kept (a quarter more are recorded to make up for the failures).
2. Twin demonstrations: planner-synthesized ID and OOD demos in the twin; with
   ``fit_look`` in the twin whose ``appearance`` (light, table colour) ``twinrl gap
   diagnose`` fitted to the real demos' images (``<task>/twin_fitted.yaml``), so that
   an image policy's twin demos look like the cell; with ``detours`` that share of
   them first strays beside the object (``twinrl expand --detours``).
3. With ``perception`` (image policy): that many twin episodes per region, half of
   them straying first and a third missing their first grasp (closed fingers holding
   nothing), under varied light, in the same twin, and a pose estimator
   trained on them (:mod:`twinrl_learn.perception`) that every image policy acts
   through.
4. SFT of one policy per data mix: real only, and real + twin (ID, OOD) =
   (30, 30), (60, 30), (30, 60) (scaled by ``scale``); the state policy reads
   ``state_inputs`` (relative by default, as in the quick pipeline) of the privileged
   object poses, and is labelled so. With ``act``, lerobot's ACT is trained on each mix
   by lerobot's own trainer, the object poses removed (:mod:`twinrl_learn.lerobot_training`):
   the external anchor.
5. Evaluation of every policy in the plant over a grid covering ID and OOD.

Writes ``out/table1.md`` (the paper's Table I shape, plus the paper's numbers for
reference), ``out/stage1.json`` and one heatmap per policy.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinrl_data.atomic import write_text_atomic
from twinrl_data.lerobot_io import export_dataset, iter_dataset_episodes
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate
from twinrl_learn.lerobot_training import (
    LEROBOT_POLICIES,
    LeRobotTraining,
    policy_dataset,
    train_lerobot_policy,
)
from twinrl_learn.perception.training import train_estimator
from twinrl_learn.reward_classifier import ClassifierSettings, train_reward_classifier
from twinrl_learn.runners import LeRobotRunner, TwinrlRunner
from twinrl_learn.settings import PerceptionSettings, SFTConfig
from twinrl_learn.sft import train_sft
from twinrl_learn.studies.settings import Stage1Settings
from twinrl_robot.scripted import run_scripted_expert
from twinrl_sim.expand import expand
from twinrl_sim.gap.diagnose import diagnose
from twinrl_sim.gap.report import write_fitted_spec
from twinrl_sim.spec import SceneSpec, load_spec
from twinrl_sim.tasks import make_task

TELEOP_NOISE = 0.002  # m per step of unsteady-hand jitter the expert-as-operator corrects
MIXES = ((0, 0), (30, 30), (60, 30), (30, 60))  # twin demos (ID, OOD) added to the real ones
POLICY_LABELS = {
    "state": "state (privileged)",
    "vla": "vla (images)",
    "act": "ACT, lerobot's (images)",
}
PERCEPTION_DETOURS = 0.5  # share of the perception episodes that stray: off-path views
# Share whose first grasp closes empty above the object: without them every closed gripper
# holds the object, and the estimator saw a missed grasp as the object in hand
# (docs/results/pipeline-quick.md#the-seeing-operators-own-takeovers).
PERCEPTION_MISSES = 0.3
# Share of their detours made with closed fingers: closed empty fingers far from the
# object, where a stalled policy leaves them, were still read as a grasp (same page).
PERCEPTION_CLOSED_DETOURS = 0.4
# The success classifier's twin episodes: the recipe that met precision and recall of
# 0.9 on unseen plant episodes of pick_place (docs/results/reward-classifier.md).
CLASSIFIER_NOISE, CLASSIFIER_SETTLE, CLASSIFIER_NEAR_MISSES, CLASSIFIER_STEPS = 0.004, 3, 0.3, 3000
PAPER_TABLE1 = {(0, 0): (40, 0), (30, 30): (70, 30), (60, 30): (80, 40), (30, 60): (70, 70)}


@dataclass
class Stage1Row:
    task: str
    policy: str
    twin_id: int
    twin_ood: int
    success: dict[str, float]


def record_real_demos(
    task: str, count: int, base: Path, *, seed: int = 0, effects: str | Path | None = None
) -> tuple[int, int]:
    """Record ``count`` successful teleop-like demos in the plant, region ID only, into
    ``base/real_session`` and export them as the LeRobotDataset ``base/real``; a quarter
    more are recorded to make up for failures. Returns (kept, recorded)."""
    session = Session.create(base / "real_session")
    report = run_scripted_expert(
        task,
        world="plant",
        episodes=math.ceil(count * 1.25),
        regions=("ID",),
        effects=effects,
        seed=seed,
        session=session,
        action_noise=TELEOP_NOISE,
    )
    kept = [
        path
        for path, episode in zip(session.episode_paths(), report.episodes, strict=True)
        if episode.success
    ][:count]
    if not kept:
        raise RuntimeError(f"{task}: no successful demo among {len(report.episodes)} recorded")
    export_dataset((read_episode(p) for p in kept), base / "real")
    return len(kept), len(report.episodes)


def fit_look(task: str, real: Path, path: Path) -> SceneSpec:
    """The task's twin with the ``appearance`` that ``twinrl gap diagnose`` fits to the
    real demos' images, saved at ``path``; refused when the fit is not significant."""
    nominal = make_task(task).scene
    episodes = list(iter_dataset_episodes(real))
    diagnosis = diagnose(episodes, nominal, allowed=["appearance"])
    if "appearance" not in diagnosis.effects:
        raise RuntimeError(f"{task}: the real demos' images name no appearance difference")
    write_fitted_spec(nominal, diagnosis, path)
    return load_spec(path)


def train_task_estimator(
    task: str, base: Path, scene: SceneSpec | None, per_region: int, *, seed: int, device: str
) -> Path:
    """Synthesize ``per_region`` twin episodes per region for perception (half of them
    straying first, two in five of those with closed fingers, a third missing their first
    grasp, under varied light) and train the pose estimator on them; returns its folder."""
    expand(
        task,
        id_count=per_region,
        ood_count=per_region,
        out=base / "perception",
        scene=scene,
        seed=seed + 2,
        export=False,
        detours=PERCEPTION_DETOURS,
        misses=PERCEPTION_MISSES,
        closed_detours=PERCEPTION_CLOSED_DETOURS,
        randomize=("lighting",),
    )
    folder = base / "estimator"
    train_estimator(
        PerceptionSettings(
            datasets=[str(base / "perception" / "session")],
            out=str(folder),
            seed=seed,
            device=device,
        )
    )
    return folder


def train_twin_classifier(
    task: str,
    base: Path,
    scene: SceneSpec | None,
    per_region: int,
    *,
    seed: int,
    device: str,
    steps: int = CLASSIFIER_STEPS,
) -> Path:
    """Record ``per_region`` scripted-expert episodes per region in the twin (a share of
    them near misses, each success held for a few steps: labels are free there) and train
    the task's success classifier on them; returns its folder."""
    session = Session.create(base / "success_session")
    run_scripted_expert(
        task,
        world="twin",
        episodes=per_region,
        scene=scene,
        seed=seed + 3,
        session=session,
        action_noise=CLASSIFIER_NOISE,
        settle=CLASSIFIER_SETTLE,
        near_misses=CLASSIFIER_NEAR_MISSES,
    )
    folder = base / "success_classifier"
    fit_twin_classifier([session.path], folder, seed=seed, device=device, steps=steps)
    return folder


def fit_twin_classifier(
    sessions: list[Path], folder: Path, *, seed: int, device: str, steps: int = CLASSIFIER_STEPS
) -> Path:
    """Train the success classifier on every episode of ``sessions`` (twin episodes,
    labelled by the twin): the scripted ones of :func:`train_twin_classifier`, and the
    pipeline adds Stage II's twin-RL rollouts, the policy's own successes and failures
    (docs/results/pipeline-quick.md#the-whole-run-real-rl-without-privileged-state)."""
    train_reward_classifier(
        [read_episode(path) for session in sessions for path in Session(session).episode_paths()],
        folder,
        ClassifierSettings(cameras=("front", "wrist"), steps=steps, seed=seed),
        device=device,
    )
    return folder


def run_stage1(
    settings: Stage1Settings, out: str | Path, log: Callable[[str], None] = print
) -> list[Stage1Row]:
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise LearnError(f"{out} exists and is not empty; choose another output folder")
    out.mkdir(parents=True, exist_ok=True)
    n = lambda count: max(1, round(count * settings.scale))  # noqa: E731 - tiny local helper
    rows: list[Stage1Row] = []
    started = time.perf_counter()
    for task in settings.tasks:
        base = out / task
        log(f"{task}: recording {n(settings.real)} noisy teleop demos in the plant (region ID)")
        kept, recorded = record_real_demos(task, n(settings.real), base, seed=settings.seed)
        log(f"{task}: keeping {kept} successful demos of {recorded} recorded")
        scene = None
        if settings.fit_look:
            scene = fit_look(task, base / "real", base / "twin_fitted.yaml")
            log(f"{task}: twin demos in the fitted look {scene.effects['appearance']}")
        most_id = max(m[0] for m in MIXES)
        most_ood = max(m[1] for m in MIXES)
        log(f"{task}: synthesizing {n(most_id)} ID + {n(most_ood)} OOD twin demos")
        expand(
            task,
            id_count=n(most_id),
            ood_count=0,
            out=base / "twin_id",
            scene=scene,
            seed=settings.seed,
            export=False,
            images=settings.needs_images,
            detours=settings.detours,
        )
        expand(
            task,
            id_count=0,
            ood_count=n(most_ood),
            out=base / "twin_ood",
            scene=scene,
            seed=settings.seed + 1,
            export=False,
            images=settings.needs_images,
            detours=settings.detours,
        )
        estimator = None
        if settings.perception and "vla" in settings.policies:
            estimator = train_task_estimator(
                task,
                base,
                scene,
                n(settings.perception),
                seed=settings.seed,
                device=settings.device,
            )
            log(f"{task}: pose estimator {estimator} (twinrl locate it on any episodes)")
        twin_id = Session(base / "twin_id" / "session").episode_paths()
        twin_ood = Session(base / "twin_ood" / "session").episode_paths()
        for mix_id, mix_ood in MIXES:
            datasets, weights = [str(base / "real")], [n(settings.real)]
            for label, paths, count in (("id", twin_id, mix_id), ("ood", twin_ood, mix_ood)):
                if count:
                    root = base / f"twin_{label}_{n(count)}"
                    if not root.exists():
                        export_dataset((read_episode(p) for p in paths[: n(count)]), root)
                    datasets.append(str(root))
                    weights.append(n(count))
            for kind in settings.policies:
                name = f"{kind}_real_id{mix_id}_ood{mix_ood}"
                log(f"{task}: SFT {name}")
                if kind in LEROBOT_POLICIES:
                    runner = _train_lerobot(kind, datasets, base / name, settings)
                else:
                    runner = _train_twinrl(
                        kind, datasets, weights, base / name, estimator, settings
                    )
                report = evaluate(
                    runner,
                    task,
                    world="plant",
                    grid=settings.grid,
                    episodes=settings.episodes_per_cell,
                    seed=settings.seed,
                    out=base / f"{name}_eval",
                )
                rows.append(Stage1Row(task, kind, mix_id, mix_ood, report.success_rate()))
                log(f"{task}: {name}: {report.success_rate()}")
    write_text_atomic(
        out / "stage1.json",
        json.dumps(
            {"rows": [r.__dict__ for r in rows], "seconds": time.perf_counter() - started}, indent=1
        ),
    )
    write_text_atomic(out / "table1.md", markdown_table(rows, settings))
    return rows


def _train_twinrl(
    kind: str,
    datasets: list[str],
    weights: list[int],
    out: Path,
    estimator: Path | None,
    settings: Stage1Settings,
) -> TwinrlRunner:
    """SFT of one of twinrl's policies on the mix, weighted by its episode counts."""
    train_sft(
        SFTConfig(
            datasets=datasets,
            weights=[float(w) for w in weights],
            out=str(out),
            policy=kind,
            steps=settings.sft_steps(kind),
            inputs=settings.state_inputs if kind == "state" else "absolute",
            perception=None if kind != "vla" or estimator is None else str(estimator),
            seed=settings.seed,
            device=settings.device,
        )
    )
    return TwinrlRunner(out, device=settings.device)


def _train_lerobot(
    kind: str, datasets: list[str], out: Path, settings: Stage1Settings
) -> LeRobotRunner:
    """lerobot's policy trained by lerobot's trainer on the mix, without the columns a
    cell cannot fill (:mod:`twinrl_learn.lerobot_training`)."""
    dataset = policy_dataset(datasets, out.with_name(out.name + "_dataset"))
    training = LeRobotTraining(
        policy=kind, steps=settings.act_steps, seed=settings.seed, device=settings.device
    )
    return LeRobotRunner(train_lerobot_policy(dataset, out, training), device=settings.device)


def markdown_table(rows: list[Stage1Row], settings: Stage1Settings) -> str:
    """The reproduction in the shape of the paper's Table I."""
    lines = [
        "# Stage I: twin demonstrations expand what SFT covers (TwinRL Table I)",
        "",
        f"{settings.real} real (plant, teleop-like) demos in region ID; twin demos added per row"
        + (
            " (synthesized in the twin with the look fitted to the real demos)"
            if settings.fit_look
            else ""
        )
        + (
            f", {100 * settings.detours:.0f} % of them straying beside the object first"
            if settings.detours
            else ""
        )
        + "; "
        f"evaluation in the plant over a {settings.grid[0]}x{settings.grid[1]} grid "
        f"({settings.episodes_per_cell} episodes per cell); the state policy reads "
        f"{settings.state_inputs} inputs of the true object poses, which only the twin and "
        "the plant know"
        + (
            f"; the image policy acts through a pose estimator trained on "
            f"{settings.perception} twin episodes per region"
            if settings.perception and "vla" in settings.policies
            else ""
        )
        + (
            f"; lerobot's ACT, trained by lerobot's own trainer ({settings.act_steps} steps, "
            "batch 16), reads the cameras and the arm's state, never the object poses"
            if "act" in settings.policies
            else ""
        )
        + ". Paper: one task, real robot.",
        "",
        "| task | policy | twin ID | twin OOD | ID SR | OOD SR | avg | paper ID | paper OOD |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ids, ood = r.success.get("ID", 0.0), r.success.get("OOD", 0.0)
        paper = PAPER_TABLE1[(r.twin_id, r.twin_ood)]
        policy = POLICY_LABELS.get(r.policy, r.policy)
        lines.append(
            f"| {r.task} | {policy} | {r.twin_id} | {r.twin_ood} | {100 * ids:.0f} % | "
            f"{100 * ood:.0f} % | {100 * np.mean([ids, ood]):.0f} % | {paper[0]} % | {paper[1]} % |"
        )
    lines += ["", "Heatmaps: `<task>/<policy>_eval/heatmap.png`."]
    return "\n".join(lines) + "\n"
