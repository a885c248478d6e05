"""Batched simulation throughput, measured side by side in one run.

Open loop (re-sending logged joint targets, as replay and demo synthesis do):

- ``python loop``: one env after the other, ``Cell.send`` per control step;
- ``raw mujoco.rollout``: one threaded call on prepared initial states and controls;
- ``BatchRollout``: twinrl's batched replay, end to end (building the initial states
  and controls from configurations included).

Closed loop (a policy acts on every observation; the scripted expert stands in):
``TwinEnv`` one env after the other versus ``BatchEnv`` with all envs at once.

Throughput is in env steps (control steps, 10 Hz) per second. Usage::

    python bench/bench_batch.py --task pick_place --episodes 32 --steps 60
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Annotated

import mujoco
import numpy as np
import typer
from mujoco import rollout as mj_rollout

from twinrl_sim.batch import BatchEnv, BatchRollout
from twinrl_sim.env import TwinEnv
from twinrl_sim.windowed import INPUTS


def main(
    task: Annotated[str, typer.Option(help="Task to simulate.")] = "pick_place",
    episodes: Annotated[int, typer.Option(help="Episodes in the batch.")] = 32,
    steps: Annotated[int, typer.Option(help="Control steps per episode.")] = 60,
    nthread: Annotated[int, typer.Option(help="Threads (default: all cores).")] = 0,
    out: Annotated[Path | None, typer.Option(help="Also write the figures as JSON here.")] = None,
) -> None:
    """Print a Markdown table of env-steps/s and ratios."""
    threads = nthread or os.cpu_count() or 1
    env = TwinEnv(task)
    rng = np.random.default_rng(0)
    configs = [env.task.sample_config(rng, ("ID", "OOD")[i % 2]) for i in range(episodes)]

    # Closed loop, one env after the other; also records the commands for open loop.
    targets = np.zeros((episodes, steps, 6))
    gripper = np.zeros((episodes, steps))
    start = time.perf_counter()
    for i, config in enumerate(configs):
        expert = env.task.expert(config, np.random.default_rng(i))
        obs, _ = env.reset(options={"config": config})
        for t in range(steps):
            action = expert.act(obs)
            obs, _, _, _, info = env.step(action)
            targets[i, t] = info["command.joint_target"]
            gripper[i, t] = action[6]
    sequential_closed = episodes * steps / (time.perf_counter() - start)

    batch_env = BatchEnv(task, episodes, nthread=threads)
    experts = [env.task.expert(c, np.random.default_rng(i)) for i, c in enumerate(configs)]
    start = time.perf_counter()
    obs = batch_env.reset(configs)
    for _ in range(steps):
        actions = np.stack(
            [e.act({k: v[i] for k, v in obs.items()}) for i, e in enumerate(experts)]
        )
        obs, *_ = batch_env.step(actions)
    batched_closed = episodes * steps / (time.perf_counter() - start)
    batch_env.close()

    # Open loop: python loop, raw rollout, BatchRollout.
    cell = env.cell
    start = time.perf_counter()
    for i, config in enumerate(configs):
        env.task.start(cell, config)
        for t in range(steps):
            cell.send(targets[i, t], gripper[i, t])
    python_open = episodes * steps / (time.perf_counter() - start)

    replayer = BatchRollout(task, nthread=threads)
    starts = replayer.initial_states(configs)
    held = replayer.engine.period_inputs(cell.model, starts, targets, gripper)
    control = np.repeat(held, cell.substeps, axis=1)
    datas = [mujoco.MjData(cell.model) for _ in range(threads)]
    with mj_rollout.Rollout(nthread=threads) as pool:
        start = time.perf_counter()
        pool.rollout(cell.model, datas, starts.state, control, control_spec=INPUTS)
        raw_open = episodes * steps / (time.perf_counter() - start)

    start = time.perf_counter()
    replayer.run(configs, targets, gripper)
    batched_open = episodes * steps / (time.perf_counter() - start)
    replayer.close()
    env.close()

    rows = [
        ("open loop", "python loop (Cell.send)", python_open, python_open / raw_open),
        ("open loop", "raw mujoco.rollout", raw_open, 1.0),
        ("open loop", "BatchRollout (end to end)", batched_open, batched_open / raw_open),
        (
            "closed loop",
            "TwinEnv, one after the other",
            sequential_closed,
            sequential_closed / raw_open,
        ),
        ("closed loop", "BatchEnv", batched_closed, batched_closed / raw_open),
    ]
    print(
        f"{task}: {episodes} episodes x {steps} control steps "
        f"({cell.substeps} physics steps each), {threads} threads\n"
    )
    print("| loop | runner | env steps/s | vs raw rollout |")
    print("|---|---|---|---|")
    for loop, name, rate, ratio in rows:
        print(f"| {loop} | {name} | {rate:,.0f} | {ratio:.2f} |")
    print(f"\nBatchEnv / TwinEnv (closed loop): {batched_closed / sequential_closed:.2f}x")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({name: rate for _, name, rate, _ in rows}, indent=1))


if __name__ == "__main__":
    typer.run(main)
