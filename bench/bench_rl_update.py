"""The RL update's cost by policy kind, side by side, and what it makes of each preset.

Twin and real RL make one gradient update per environment step (``utd``), and on CPU
the updates, not the simulation, set how long a pipeline takes. This times the TwinRL
agent's update (critic ensemble + actor, batch 64, chunks as SFT makes them) for the
state policy and the image policy on the same few twin demos, prints their ratio, and
multiplies each by the number of updates a preset's pipeline makes (Stage II, then four
methods x seeds of real RL, each with its offline phase). Usage::

    python bench/bench_rl_update.py --updates 20
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import typer

from twinrl_data.cli import quiet_encoders
from twinrl_learn.agent import Agent, RLConfig
from twinrl_learn.pipeline import METHOD_TABLE, PRESETS, Preset
from twinrl_learn.policy import Policy
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.sft import SFTConfig, train_sft
from twinrl_sim.expand import expand


def seconds_per_update(checkpoint: Path, dataset: str, updates: int) -> float:
    """Mean wall time of one TwinRL update on batches drawn from ``dataset``."""
    policy = Policy.from_pretrained(checkpoint)
    agent = Agent(policy, RLConfig.for_method("twinrl", seed=0))
    cameras = policy.config.cameras if policy.needs_images else ()
    buffer = ReplayBuffer.from_datasets([dataset], cameras=cameras)
    rng = np.random.default_rng(0)

    def batch():
        return buffer.sample(agent.config.batch_size, rng, chunk=policy.config.chunk, gamma=0.98)

    agent.update(batch())  # warm-up: first-call allocations
    start = time.perf_counter()
    for _ in range(updates):
        agent.update(batch())
    return (time.perf_counter() - start) / updates


def pipeline_updates(preset: Preset) -> int:
    """Gradient updates of a preset's pipeline: Stage II and every real-RL run, each with
    its offline phase (HiL-SERL has none)."""
    utd = RLConfig().utd
    count = utd * preset.twin_rl_steps + preset.offline_steps
    for method in METHOD_TABLE:
        offline = preset.offline_steps if RLConfig.for_method(method.rl_method).offline_steps else 0
        count += len(preset.seeds) * (utd * preset.plant_steps + offline)
    return round(count)


def main(
    updates: Annotated[int, typer.Option(help="Timed updates per policy kind.")] = 20,
    demos: Annotated[int, typer.Option(help="Twin demos (with cameras) to sample from.")] = 4,
) -> None:
    quiet_encoders()
    torch.set_num_threads(2)
    root = Path(tempfile.mkdtemp(prefix="twinrl-rl-update-"))
    try:
        report = expand("pick_place", id_count=demos // 2, ood_count=demos - demos // 2,
                        out=root / "demos", workers=1)  # fmt: skip
        seconds = {}
        for kind in ("state", "vla"):
            checkpoint = root / kind
            train_sft(SFTConfig(datasets=[report.dataset], out=str(checkpoint), policy=kind,
                                steps=1))  # fmt: skip
            seconds[kind] = seconds_per_update(checkpoint, report.dataset, updates)
    finally:
        shutil.rmtree(root)
    print(f"TwinRL update, batch 64, {torch.get_num_threads()} threads, mean of {updates}\n")
    print("| policy | s / update |\n|---|---|")
    for kind, value in seconds.items():
        print(f"| {kind} | {value:.3f} |")
    print(f"\nimage / state: {seconds['vla'] / seconds['state']:.1f}x\n")
    print("| preset | policy | updates | hours of updates |\n|---|---|---|---|")
    for name in ("quick", "paper"):
        preset = PRESETS[name]
        count = pipeline_updates(preset)
        hours = count * seconds[preset.policy] / 3600
        print(f"| {name} | {preset.policy} | {count:,} | {hours:.1f} |")


if __name__ == "__main__":
    typer.run(main)
