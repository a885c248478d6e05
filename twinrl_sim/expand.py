"""Exploration-space expansion: synthesize twin demonstrations in ID and OOD regions.

``expand(...)`` samples configurations per region, makes each demonstration with the
planner or by re-targeting one recorded demo, executes it in twin physics (both cameras
rendered, optionally visually randomised; or no cameras at all for a policy that reads
the state only, several times faster), keeps the successes as ``twin_demo`` episodes
in a session and exports them as a LeRobotDataset::

    OUT/
      session/      manifest.json + episodes/*.mcap   (every kept demonstration)
      dataset/      LeRobotDataset v3                  (what SFT reads)
      expand.json   counts, yield per region, seconds

Attempts run in worker processes, or as Ray tasks on a cluster (``cluster``); attempt
``k`` of a region always uses the same configuration and seed, so a run is reproducible
for a given seed whatever the number of workers or machines.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_data.executor import cluster_address, make_executor
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import EpisodeFolder, Recorder
from twinrl_data.schema import Episode, EpisodeMeta, step_record
from twinrl_data.session import Session
from twinrl_sim.augment import retarget
from twinrl_sim.env import TwinEnv
from twinrl_sim.errors import TwinError
from twinrl_sim.planner import plan_demo
from twinrl_sim.randomize import check_kinds, randomize_scene
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import TaskConfig, make_task

METHODS = ("plan", "augment")
DETOUR_TAG = "+detour"  # ends the policy name of a demo that strayed first
CLOSED_TAG = "+closed"  # follows DETOUR_TAG when the demo strayed with closed fingers
MISS_TAG = "+miss"  # ends the policy name of a demo whose first grasp missed
MAX_ATTEMPTS_PER_DEMO = 4


@dataclass
class ExpandReport:
    """What an expansion produced."""

    task: str
    method: str
    requested: dict[str, int]
    kept: dict[str, int] = field(default_factory=dict)
    attempts: dict[str, int] = field(default_factory=dict)
    detoured: dict[str, int] = field(default_factory=dict)  # kept demos that strayed first
    closed: dict[str, int] = field(default_factory=dict)  # of which with closed fingers
    missed: dict[str, int] = field(default_factory=dict)  # kept demos that missed first
    seconds_synthesis: float = 0.0
    seconds_export: float = 0.0
    session: str = ""
    dataset: str = ""

    @property
    def yield_rate(self) -> dict[str, float]:
        return {r: self.kept.get(r, 0) / max(self.attempts.get(r, 0), 1) for r in self.requested}

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "yield": self.yield_rate}


@dataclass(frozen=True)
class _Job:
    task: str
    region: str
    attempt: int
    seed: int
    method: str
    randomize: tuple[str, ...]
    demo_path: str | None
    episode_dir: str
    scene: SceneSpec | None = None  # the twin to synthesize in (None: the task's cell)
    images: bool = True  # render and record the cameras
    detours: float = 0.0  # share of planned demos that stray first (planner.detour_waypoint)
    misses: float = 0.0  # share of planned demos whose first grasp closes high (plan_demo)
    closed_detours: float = 0.0  # share of the detours made with closed fingers (plan_demo)


_WORKER_CACHE: dict[tuple, Any] = {}  # per worker: twin envs by scene, demos by path


def _run_job(job: _Job) -> tuple[_Job, dict[str, Any] | None]:
    """Make one demonstration; write it only if it succeeds. Runs in a worker."""
    rng = np.random.default_rng([job.seed, 0 if job.region == "ID" else 1, job.attempt])
    task = make_task(job.task, job.scene)
    config = task.sample_config(rng, job.region)
    scene, record = task.scene, {}
    if job.randomize:
        scene, record = randomize_scene(task.scene, rng, job.randomize)
    key = (scene.digest, job.images)
    env = _WORKER_CACHE.get(key)
    if env is None:
        if len(_WORKER_CACHE) > 8:
            for old in _WORKER_CACHE.values():
                if isinstance(old, TwinEnv):  # the cache also holds the demo to re-target
                    old.close()
            _WORKER_CACHE.clear()
        env = TwinEnv(job.task, scene=scene, images=job.images)
        _WORKER_CACHE[key] = env
    policy = f"synthesis:{job.method}"
    if job.method == "plan":
        # Its own stream: whether and where attempt k strays leaves its configuration, its
        # grasp and every other attempt as they are without detours.
        stream = [job.seed, 0 if job.region == "ID" else 1, job.attempt]
        draw = np.random.default_rng([*stream, 1])
        detour = draw if draw.random() < job.detours else None
        draw = np.random.default_rng([*stream, 2])
        miss = draw if draw.random() < job.misses else None
        closed = detour is not None and np.random.default_rng([*stream, 3]).random() < (
            job.closed_detours
        )
        plan = plan_demo(
            env.task, env.cell, config, rng, detour=detour, miss=miss, closed_detour=closed
        )
        if plan is None:
            return job, None
        actions = plan.actions
        policy += (DETOUR_TAG if detour is not None else "") + (CLOSED_TAG if closed else "")
        policy += MISS_TAG if miss else ""
    else:
        demo = _WORKER_CACHE.get(("demo", job.demo_path))
        if demo is None:
            demo = read_episode(job.demo_path)
            _WORKER_CACHE[("demo", job.demo_path)] = demo
        source = TaskConfig.from_dict(demo.meta.config)
        task = env.task
        actions = retarget(
            demo,
            source,
            config,
            releases_object=task.releases_object,
            grasp_period=task.grasp_period,
            grasp_yaw_offset=task.grasp_yaw_offset,
        )
    obs, info = env.reset(options={"config": config})
    steps = []
    for t, action in enumerate(actions[: env.max_steps]):
        next_obs, reward, terminated, _, info = env.step(action)
        done = terminated or t == min(len(actions), env.max_steps) - 1
        steps.append(
            step_record(obs, action, info["command.joint_target"], reward, done, terminated)
        )
        obs = next_obs
        if terminated:
            break
    if not info["success"]:
        return job, None
    meta = env.task.episode_meta(
        source="twin_demo",
        world="twin",
        names=env.cell.contract_names(),
        config=config,
        region=job.region,
        policy=policy,
        randomization=record,
    )
    recorder = Recorder(EpisodeFolder(job.episode_dir, prefix=f"{job.region}_{job.attempt:05d}_"))
    recorder.start_episode(meta)
    for step in steps:
        recorder.add_frame(step)
    path = recorder.save_episode()
    assert recorder.saved is not None
    return job, {"path": str(path), "meta": recorder.saved.to_dict(), "length": len(steps)}


def expand(
    task: str,
    *,
    id_count: int,
    ood_count: int,
    out: str | Path,
    method: str = "plan",
    from_demo: str | Path | None = None,
    randomize: tuple[str, ...] = (),
    scene: SceneSpec | None = None,
    seed: int = 0,
    workers: int | None = None,
    export: bool = True,
    images: bool = True,
    detours: float = 0.0,
    misses: float = 0.0,
    closed_detours: float = 0.0,
    force: bool = False,
    on_demo: Callable[[str, bool], None] | None = None,
    cluster: str = "",
) -> ExpandReport:
    """Synthesize ``id_count`` + ``ood_count`` successful demonstrations of ``task``.

    ``method`` is ``plan`` (grasp sampling + collision-checked waypoints) or ``augment``
    (re-target the episode ``from_demo``, an .mcap file). ``scene`` is the twin to
    synthesize in (e.g. one fitted by ``twinrl gap diagnose``: its physics and its look);
    ``None`` is the task's built-in cell. ``images=False`` records no camera frames
    (demos for a state policy: no rendering, no video encoding). ``detours`` is the
    share of planned demos whose arm first strays beside the object and does the task
    from there (off-path views and returns for an image policy; drawn per attempt, so the
    others stay as they are). ``misses`` is the share whose first grasp closes above the
    object, lifts empty-handed, opens and grasps again (closed empty fingers, and the
    recovery, for a pose estimator or an image policy). ``closed_detours`` is the share
    of the detours made with the fingers closed, opened on the way back (closed fingers
    holding nothing, far from the object: a pose estimator must not read them as a
    grasp; never for a policy's demos). ``on_demo(region, kept)`` is
    called after each attempt (for progress bars). ``cluster`` runs the attempts on Ray
    (:func:`twinrl_data.executor.cluster_address`; ``workers`` defaults to its CPUs) and
    needs ``out`` on storage every node of the cluster sees.
    """
    make_task(task, scene)
    if method not in METHODS:
        raise SettingError("method", f"must be one of {', '.join(METHODS)}, got '{method}'")
    if method == "augment":
        if from_demo is None:
            raise TwinError("`method` augment needs `from_demo`, a recorded demonstration (.mcap)")
        demo = read_episode(from_demo)
        if demo.meta.task != task:
            raise SettingError("from_demo", f"is a {demo.meta.task} episode, not {task}")
    elif from_demo is not None:
        raise SettingError("from_demo", "is only used with `method` augment")
    for name, share in (
        ("detours", detours),
        ("misses", misses),
        ("closed_detours", closed_detours),
    ):
        if not 0.0 <= share <= 1.0:
            raise SettingError(name, f"is a share of the demos, from 0 to 1; got {share}")
        if share and method != "plan":
            raise SettingError(name, "applies to `method` plan (a re-targeted demo keeps its path)")
    if closed_detours and not detours:
        raise SettingError("closed_detours", "is a share of the detours; ask for `detours` too")
    if id_count < 0 or ood_count < 0 or id_count + ood_count == 0:
        raise TwinError("ask for at least one demonstration (`id_count` and/or `ood_count`)")
    check_kinds(randomize)
    on_cluster = cluster_address(cluster) is not None
    if randomize and not images:
        raise TwinError("`randomize` changes only what the cameras see; drop it or record images")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        if not force:
            raise TwinError(
                f"{out} exists and is not empty; choose another folder or replace it (`force`)"
            )
        shutil.rmtree(out)
    session = Session.create(out / "session")
    report = ExpandReport(task=task, method=method, requested={"ID": id_count, "OOD": ood_count})
    common = {
        "seed": seed,
        "method": method,
        "randomize": tuple(randomize),
        "demo_path": str(from_demo) if from_demo else None,
        "episode_dir": str(session.path / "episodes"),
        "scene": scene,
        "images": images,
        "detours": detours,
        "misses": misses,
        "closed_detours": closed_detours,
    }
    if not on_cluster:
        workers = workers or min(2, os.cpu_count() or 1)
    start = time.perf_counter()
    with make_executor(workers, cluster=cluster) as executor:
        workers = executor.workers
        for region, count in (("ID", id_count), ("OOD", ood_count)):
            report.kept[region] = report.attempts[region] = 0
            report.detoured[region] = report.closed[region] = report.missed[region] = 0
            attempt = 0
            # Waves of attempts in attempt order: results do not depend on the workers.
            while report.kept[region] < count and attempt < count * MAX_ATTEMPTS_PER_DEMO:
                wave = max(workers, count - report.kept[region])
                jobs = [
                    _Job(task=task, region=region, attempt=attempt + i, **common)
                    for i in range(wave)
                ]
                attempt += wave
                for _, result in executor.map(_run_job, jobs):
                    if report.kept[region] >= count:
                        if result is not None:
                            Path(result["path"]).unlink()  # made in the same wave, not needed
                        continue
                    report.attempts[region] += 1
                    if result is not None:
                        meta = EpisodeMeta.from_dict(result["meta"])
                        session.register(Path(result["path"]), meta, result["length"])
                        report.kept[region] += 1
                        report.detoured[region] += DETOUR_TAG in meta.policy
                        report.closed[region] += CLOSED_TAG in meta.policy
                        report.missed[region] += meta.policy.endswith(MISS_TAG)
                    if on_demo is not None:
                        on_demo(region, result is not None)
    report.seconds_synthesis = time.perf_counter() - start
    report.session = str(session.path)
    if export and sum(report.kept.values()):
        start = time.perf_counter()
        episodes: Iterator[Episode] = (read_episode(p) for p in session.episode_paths())
        export_dataset(episodes, out / "dataset", repo_id=f"twinrl/{task}_twin_demos")
        report.seconds_export = time.perf_counter() - start
        report.dataset = str(out / "dataset")
    write_text_atomic(out / "expand.json", json.dumps(report.to_json(), indent=1))
    return report
