"""The robot loop during real RL, side by side: its period and what it learns.

A real arm is commanded at the control rate (10 Hz: a 100 ms period); a loop that
stops for a gradient update (about 0.2 s for the image policy on a CPU) stalls the arm.
This trains a starting policy on a few twin demos, then runs ``--steps`` plant steps of
real RL from it (TwinRL agent, the simulated operator) and timestamps every control
step the plant executes: the period is the time between two steps of an episode. It
prints the period's median, 99th percentile and worst, and the evaluations' success
per region over plant minutes (the learning curve). With ``--before REV`` the same runs
are made, in the same invocation, with the code at git revision ``REV`` (checked out
into a temporary worktree, run in a subprocess), so both are measured side by side on
one machine. Usage::

    # the period with the image policy
    python bench/bench_control_loop.py --steps 300 [--before REV]
    # learning curves with the state policy
    python bench/bench_control_loop.py --policy state --demos 40 --sft-steps 1500 \\
        --offline-steps 200 --steps 3000 --eval-every 600 --eval-grid 4 --seeds 2 [--before REV]

The plant itself steps as fast as it can (it counts its own time), so the period is
what the loop costs beyond the arm's own motion: on a real cell that must stay well
under the control period.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

ROOT = Path(__file__).resolve().parents[1]
app = typer.Typer(add_completion=False)


def _instrument() -> tuple[list[list[float]], list[float]]:
    """Timestamp every step of the first robot backend created (the training cell; the
    evaluation cells come later) and time every gradient update."""
    from twinrl_learn.agent import Agent

    try:  # the robot protocol's backend
        from twinrl_robot.simulated import SimulatedCell as Backend
    except ImportError:  # code from before the robot protocol: the plant itself
        from twinrl_robot.plant import Plant as Backend

    episodes: list[list[float]] = []
    updates: list[float] = []
    first: list[object] = []
    init, reset, act, update = Backend.__init__, Backend.reset, Backend.act, Agent.update

    def timed_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        if not first:
            first.append(self)

    def timed_reset(self, config):
        if first and self is first[0]:
            episodes.append([])
        return reset(self, config)

    def timed_act(self, action):
        if first and self is first[0]:
            episodes[-1].append(time.perf_counter())
        return act(self, action)

    def timed_update(self, batch):
        start = time.perf_counter()
        result = update(self, batch)
        updates.append(time.perf_counter() - start)
        return result

    Backend.__init__, Backend.reset, Backend.act = timed_init, timed_reset, timed_act
    Agent.update = timed_update
    return episodes, updates


@app.command()
def probe(spec: str) -> None:
    """(Internal) one real-RL run from a JSON ``spec``, instrumented; prints its timings
    and evaluations as JSON."""
    import torch

    from twinrl_learn.real_rl import RealRL, RealRLSettings
    from twinrl_learn.settings import RLConfig

    run = json.loads(spec)
    torch.set_num_threads(run["threads"])
    episodes, updates = _instrument()
    settings = RealRLSettings(
        task="pick_place",
        init=run["init"],
        out=run["out"],
        demos=[run["demos"]],
        plant_steps=run["steps"],
        eval_every=run["eval_every"],
        eval_grid=tuple(run["eval_grid"]),
        refresh_every=0,
        show_resets=False,
        rl=RLConfig.for_method("twinrl", offline_steps=run["offline_steps"], seed=run["seed"]),
    )
    start = time.perf_counter()
    RealRL.start(settings).run()
    seconds = time.perf_counter() - start
    periods = [float(b - a) for stamps in episodes for a, b in itertools.pairwise(stamps)]
    evaluations = json.loads((Path(run["out"]) / "evaluations.json").read_text())
    import twinrl_learn

    code = str(Path(twinrl_learn.__file__).parents[1])
    print(json.dumps({"code": code, "periods": periods, "updates": updates, "seconds": seconds,
                      "evaluations": evaluations}))  # fmt: skip


def _run_probe(tree: Path, spec: dict) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    command = [sys.executable, str(Path(__file__).resolve()), "probe", json.dumps(spec)]
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"the run in {tree} failed:\n{done.stderr[-3000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if Path(result["code"]).resolve() != tree.resolve():
        raise SystemExit(f"the run meant for {tree} imported twinrl from {result['code']}")
    return result


def _timing_row(label: str, results: list[dict]) -> str:
    periods = np.concatenate([r["periods"] for r in results]) * 1000
    updates = np.concatenate([r["updates"] for r in results]) * 1000
    seconds = np.mean([r["seconds"] for r in results])
    return (
        f"| {label} | {len(periods)} | {np.percentile(periods, 50):.1f} | "
        f"{np.percentile(periods, 99):.1f} | {periods.max():.1f} | {np.mean(updates):.0f} | "
        f"{seconds:.0f} |"
    )


def _curve_rows(label: str, results: list[dict]) -> list[str]:
    """Mean evaluation success per region over the seeds, at each evaluation."""
    rows = []
    for points in zip(*(r["evaluations"] for r in results), strict=True):
        minutes = points[0]["plant_minutes"]
        rates = {
            region: np.mean([p["success_rate"][region] for p in points]) for region in ("ID", "OOD")
        }
        rows.append(
            f"| {label} | {minutes:.1f} | {100 * rates['ID']:.0f} | {100 * rates['OOD']:.0f} |"
        )
    return rows


@app.command()
def main(
    policy: Annotated[str, typer.Option(help="vla (the image policy) or state.")] = "vla",
    steps: Annotated[int, typer.Option(help="Plant steps of real RL per run.")] = 300,
    before: Annotated[
        str | None, typer.Option(help="Also run the code at this git revision, side by side.")
    ] = None,
    demos: Annotated[int, typer.Option(help="Twin demos to train the SFT policy on.")] = 4,
    sft_steps: Annotated[int, typer.Option(help="SFT steps of the starting policy.")] = 20,
    offline_steps: Annotated[int, typer.Option(help="Offline updates before real RL.")] = 0,
    eval_every: Annotated[
        int, typer.Option(help="Plant steps between evaluations (0: at the start and end).")
    ] = 0,
    eval_grid: Annotated[int, typer.Option(help="Evaluation grid size N (NxN).")] = 2,
    seeds: Annotated[int, typer.Option(help="Runs per code, seeds 0..N-1.")] = 1,
    threads: Annotated[
        int, typer.Option(help="Torch threads per process (twinrl train real-rl uses 1).")
    ] = 1,
) -> None:
    from twinrl_data.console import quiet_encoders
    from twinrl_learn.settings import SFTConfig
    from twinrl_learn.sft import train_sft
    from twinrl_sim.expand import expand

    quiet_encoders()
    root = Path(tempfile.mkdtemp(prefix="twinrl-control-loop-"))
    worktree = root / "before"
    trees = {"this tree": ROOT}
    try:
        report = expand("pick_place", id_count=demos // 2, ood_count=demos - demos // 2,
                        out=root / "demos", workers=1, images=policy == "vla")  # fmt: skip
        init = root / "sft"
        inputs = "relative" if policy == "state" else "absolute"
        train_sft(SFTConfig(datasets=[report.dataset], out=str(init), policy=policy,
                            steps=sft_steps, inputs=inputs))  # fmt: skip
        if before is not None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(worktree),
                            before], check=True, capture_output=True)  # fmt: skip
            trees = {f"before ({before})": worktree, **trees}
        runs: dict[str, list[dict]] = {}
        for label, tree in trees.items():
            runs[label] = [
                _run_probe(
                    tree,
                    {
                        "init": str(init),
                        "demos": report.dataset,
                        "steps": steps,
                        "out": str(root / f"run_{len(runs)}_{seed}"),
                        "threads": threads,
                        "eval_every": eval_every,
                        "eval_grid": [eval_grid, eval_grid],
                        "offline_steps": offline_steps,
                        "seed": seed,
                    },
                )
                for seed in range(seeds)
            ]
    finally:
        if worktree.exists():
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force",
                            str(worktree)], check=False, capture_output=True)  # fmt: skip
        shutil.rmtree(root, ignore_errors=True)
    print(f"real RL with the {policy} policy, {steps} plant steps x {seeds} seed(s), "
          f"{threads} torch thread(s)\n")  # fmt: skip
    print("| code | periods | p50 (ms) | p99 (ms) | max (ms) | update, mean (ms) | run (s) |")
    print("|---|---|---|---|---|---|---|")
    for label, results in runs.items():
        print(_timing_row(label, results))
    print(f"\nevaluation success (%, mean of {seeds} seed(s), {eval_grid}x{eval_grid} grid)\n")
    print("| code | plant minutes | ID | OOD |\n|---|---|---|---|")
    for label, results in runs.items():
        print("\n".join(_curve_rows(label, results)))


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] != "probe":
        sys.argv.insert(1, "main")
    app()
