"""Scale-out: twin demo synthesis (`twinrl expand`) and twin RL's environments
(:class:`~twinrl_sim.sharded.ShardedBatchEnv`) on this machine's worker processes
against Ray embedded on this machine, for 1 and 2 workers, side by side in one run.

Each backend's start-up (the executor made, a trivial job on every worker, closed) is
timed apart from its synthesis; the throughput is attempts per second of synthesis
once started. Ray's
overhead is its time over the processes' for the same workers and the same attempts
(which must keep the same demonstrations: same seed, same results). From Ray's rate
per worker it estimates a paper-scale synthesis on ``machines`` machines of ``cores``
cores each, assuming jobs scale linearly (they share nothing but the output folder).

Twin RL's environments: ``envs`` pick-and-place envs stepped ``steps`` times with the
same seeded actions, in this process (one worker) or in shards, with and without the
two cameras; env-steps per second once the shards are up, and the observations of
every variant checked equal.

The pipeline (``twinrl demo``, the ``--preset``'s whole run: Stage I, twin RL, mining
and every method's real-RL run) end to end with 1 and 2 worker processes and with 1
and 2 Ray workers: wall time, and its ratio to one worker process; every run's report
must hold the same results. Usage::

    MUJOCO_GL=egl python bench/bench_scale.py --demos 40 --envs 8 --steps 60
    MUJOCO_GL=egl python bench/bench_scale.py --preset none   # without the pipeline
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from twinrl_data.executor import make_executor
from twinrl_learn.studies.pipeline import run_demo
from twinrl_sim.batch import BatchEnv
from twinrl_sim.expand import ExpandReport, expand
from twinrl_sim.sharded import ShardedBatchEnv
from twinrl_sim.tasks import make_task

BACKENDS = {"processes": "", "Ray (embedded)": "local"}


def started(workers: int, cluster: str) -> float:
    """Seconds to start the executor, run a trivial job on each worker and stop it."""
    start = time.perf_counter()
    with make_executor(workers, cluster=cluster) as executor:
        executor.map(abs, range(workers))
    return time.perf_counter() - start


def synthesized(task: str, demos: int, workers: int, cluster: str) -> ExpandReport:
    out = Path(tempfile.mkdtemp(prefix="twinrl-scale-")) / "run"
    try:
        return expand(
            task,
            id_count=demos // 2,
            ood_count=demos - demos // 2,
            out=out,
            seed=3,
            workers=workers,
            images=False,
            export=False,
            cluster=cluster,
        )
    finally:
        shutil.rmtree(out.parent)


def stepped(
    envs: int, steps: int, workers: int, cluster: str, cameras: tuple[str, ...]
) -> tuple[float, np.ndarray]:
    """(env-steps per second once started, the last observation's state rows) of
    ``envs`` envs stepped ``steps`` times with seeded actions."""
    task = make_task("pick_place")
    rng = np.random.default_rng(0)
    configs = [task.sample_config(rng).to_dict() for _ in range(envs)]
    actions = rng.uniform(-1.0, 1.0, (steps, envs, 7)) * [0.01, 0.01, 0.01, 0.05, 0.05, 0.05, 1]
    actions[:, :, 6] = actions[:, :, 6] > 0  # the gripper opened or closed
    with make_executor(workers, cluster=cluster) as executor:
        if workers == 1 and not cluster:
            env: BatchEnv | ShardedBatchEnv = BatchEnv(task, envs, cameras=cameras)
        else:
            env = ShardedBatchEnv(task, envs, executor, cameras=cameras)
        try:
            env.reset(configs)
            start = time.perf_counter()
            for row in actions:
                obs, *_ = env.step(row)
            seconds = time.perf_counter() - start
        finally:
            env.close()
    return envs * steps / seconds, obs["observation.state"]


def main(
    task: Annotated[str, typer.Option(help="Task to synthesize.")] = "pick_place",
    demos: Annotated[int, typer.Option(help="Demonstrations, half ID, half OOD.")] = 40,
    paper_demos: Annotated[int, typer.Option(help="Demonstrations of the estimate.")] = 1000,
    machines: Annotated[int, typer.Option(help="Machines of the estimate.")] = 4,
    cores: Annotated[int, typer.Option(help="Cores per machine of the estimate.")] = 16,
    envs: Annotated[int, typer.Option(help="Twin RL environments.")] = 8,
    steps: Annotated[int, typer.Option(help="Vector steps of the environments.")] = 60,
    preset: Annotated[
        str, typer.Option(help="Pipeline preset timed end to end (none: skip it).")
    ] = "smoke",
) -> None:
    _environments(envs, steps, machines, cores)
    rows, reports = [], {}
    for workers in (1, 2):
        for name, cluster in BACKENDS.items():
            start_s = started(workers, cluster)
            report = synthesized(task, demos, workers, cluster)
            attempts = sum(report.attempts.values())
            run_s = max(report.seconds_synthesis - start_s, 1e-9)
            rows.append((workers, name, start_s, report.seconds_synthesis, attempts / run_s))
            reports[workers, name] = (report.kept, report.attempts)
    kept, attempts = next(iter(reports.values()))
    assert all(r == (kept, attempts) for r in reports.values()), f"other demos: {reports}"
    print(f"{task}: {sum(kept.values())} demos, {sum(attempts.values())} attempts, no cameras\n")
    print("| workers | backend | start-up (s) | synthesis (s) | attempts/s after start-up |")
    print("|---|---|---|---|---|")
    for workers, name, start_s, total_s, rate in rows:
        print(f"| {workers} | {name} | {start_s:.1f} | {total_s:.1f} | {rate:.2f} |")
    by = {(w, n): (s, t, r) for w, n, s, t, r in rows}
    print()
    for workers in (1, 2):
        (ps, pt, pr), (rs, rt, rr) = by[workers, "processes"], by[workers, "Ray (embedded)"]
        print(
            f"{workers} worker(s): Ray/processes wall time {rt / pt:.2f}, start-up "
            f"{rs - ps:+.1f} s, throughput after start-up {rr / pr:.2f}"
        )
    per_worker = by[2, "Ray (embedded)"][2] / 2
    yield_rate = sum(kept.values()) / sum(attempts.values())
    rate = per_worker * machines * cores
    print(
        f"\nestimate: {paper_demos} demos on {machines} machines x {cores} cores at "
        f"{per_worker:.2f} attempts/s per worker and a {100 * yield_rate:.0f} % yield: "
        f"{paper_demos / yield_rate / rate:.0f} s of synthesis (plus the cluster's start-up)"
    )
    if preset != "none":
        _pipeline(preset)


def piped(preset: str, workers: int, cluster: str) -> tuple[float, dict]:
    """(wall seconds, the report's results) of one whole pipeline run."""
    out = Path(tempfile.mkdtemp(prefix="twinrl-scale-pipeline-")) / "run"
    try:
        start = time.perf_counter()
        report = run_demo(
            "pick_place", preset, out, workers=workers, cluster=cluster, device="cpu",
            log=lambda message: None,
        )  # fmt: skip
        return time.perf_counter() - start, {k: report[k] for k in ("stages", "methods")}
    finally:
        shutil.rmtree(out.parent)


def _pipeline(preset: str) -> None:
    print(f"\nthe pipeline, preset {preset}, end to end\n")
    print("| workers | backend | wall time (s) | ratio to one worker |")
    print("|---|---|---|---|")
    alone, results = piped(preset, 1, "")
    print(f"| 1 | processes | {alone:.0f} | 1.00 |")
    for workers in (1, 2):
        for name, cluster in BACKENDS.items():
            if (workers, cluster) == (1, ""):
                continue
            seconds, theirs = piped(preset, workers, cluster)
            assert theirs == results, f"{name}: other results with {workers} worker(s)"
            print(f"| {workers} | {name} | {seconds:.0f} | {seconds / alone:.2f} |")


def _environments(envs: int, steps: int, machines: int, cores: int) -> None:
    print(f"twin RL environments: {envs} pick_place envs, {steps} vector steps\n")
    print("| cameras | workers | backend | env-steps/s | ratio to one process |")
    print("|---|---|---|---|---|")
    for cameras in ((), ("front", "wrist")):
        alone, states = stepped(envs, steps, 1, "", cameras)
        label = "front, wrist" if cameras else "none"
        print(f"| {label} | 1 | in the process | {alone:.0f} | 1.00 |")
        for name, cluster in BACKENDS.items():
            rate, theirs = stepped(envs, steps, 2, cluster, cameras)
            assert np.array_equal(states, theirs), f"{name}: other observations"
            print(f"| {label} | 2 | {name} | {rate:.0f} | {rate / alone:.2f} |")
        per_worker = rate / 2
    print(
        f"\nestimate, with cameras: {machines} machines x {cores} cores at {per_worker:.0f} "
        f"env-steps/s per Ray worker: {per_worker * machines * cores:.0f} env-steps/s, if "
        "the learner's machine keeps up with their observations\n"
    )


if __name__ == "__main__":
    typer.run(main)
