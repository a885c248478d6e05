"""The RL update's cost by policy kind, side by side, and what it makes of each preset.

Twin and real RL make one gradient update per environment step (``utd``), and on CPU
the updates, not the simulation, set how long a pipeline takes. This times the TwinRL
agent's update (critic ensemble + actor, batch 64, chunks as SFT makes them) for the
state policy, the image policy with its own encoders and the image policy acting through
a pose estimator (whose estimates the replay buffer computes once per episode) on the
same few twin demos, offline (with the Cal-QL regulariser) and online, prints their
ratios, and multiplies each by the number of
updates a preset's pipeline makes (Stage II, then four methods x seeds of real RL, each
with its offline phase). Usage::

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

from twinrl_data.console import quiet_encoders
from twinrl_learn.agent import Agent
from twinrl_learn.perception import train_estimator
from twinrl_learn.policy import Policy
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.settings import PerceptionSettings, RLConfig, SFTConfig
from twinrl_learn.sft import train_sft
from twinrl_learn.studies.presets import (
    METHOD_TABLE,
    PRESETS,
    Preset,
    real_rl_config,
    twin_rl_config,
)
from twinrl_sim.expand import expand

LABELS = ("state", "vla", "vla through an estimator")


def seconds_per_update(
    checkpoint: Path, buffer: ReplayBuffer, updates: int, offline: bool
) -> float:
    """Mean wall time of one TwinRL update on batches drawn from ``buffer``: an offline
    one (with the Cal-QL regulariser) or an online one, from the checkpoint afresh."""
    policy = Policy.from_pretrained(checkpoint)
    config = RLConfig.for_method("twinrl", seed=0, offline_steps=updates + 1 if offline else 0)
    agent = Agent(policy, config)
    rng = np.random.default_rng(0)

    def batch():
        return buffer.sample(config.batch_size, rng, chunk=policy.config.chunk, gamma=config.gamma)

    agent.update(batch())  # warm-up: first-call allocations
    start = time.perf_counter()
    for _ in range(updates):
        agent.update(batch())
    return (time.perf_counter() - start) / updates


def pipeline_updates(preset: Preset) -> tuple[int, int]:
    """Offline and online gradient updates of a preset's pipeline: Stage II and every
    real-RL run, each with the RL settings the pipeline gives it."""
    configs = [(twin_rl_config(preset), preset.twin_rl_steps)]
    configs += [
        (real_rl_config(method, preset, seed), preset.plant_steps)
        for method in METHOD_TABLE
        for seed in preset.seeds
    ]
    offline = sum(config.offline_steps for config, _ in configs)
    return offline, round(sum(config.utd * steps for config, steps in configs))


def main(
    updates: Annotated[int, typer.Option(help="Timed updates per policy kind and phase.")] = 20,
    demos: Annotated[int, typer.Option(help="Twin demos (with cameras) to sample from.")] = 4,
) -> None:
    quiet_encoders()
    torch.set_num_threads(2)
    root = Path(tempfile.mkdtemp(prefix="twinrl-rl-update-"))
    try:
        report = expand("pick_place", id_count=demos // 2, ood_count=demos - demos // 2,
                        out=root / "demos", workers=1)  # fmt: skip
        estimator = root / "estimator"
        train_estimator(PerceptionSettings(datasets=[report.dataset], out=str(estimator),
                                           steps=1))  # fmt: skip
        seconds = {}
        for label in LABELS:
            kind = label.split()[0]
            checkpoint = root / label.replace(" ", "_")
            perception = str(estimator) if "estimator" in label else None
            train_sft(SFTConfig(datasets=[report.dataset], out=str(checkpoint), policy=kind,
                                steps=1, perception=perception))  # fmt: skip
            views = Policy.from_pretrained(checkpoint).replay_views()
            buffer = ReplayBuffer.from_datasets([report.dataset], **views)
            buffer.valid_starts(1)  # the estimates, computed once, before the timing
            for phase in ("offline", "online"):
                seconds[label, phase] = seconds_per_update(
                    checkpoint, buffer, updates, offline=phase == "offline"
                )
    finally:
        shutil.rmtree(root)
    batch = RLConfig().batch_size
    print(f"TwinRL update, batch {batch}, {torch.get_num_threads()} threads, mean of {updates}\n")
    print("| policy | offline s / update | online s / update |\n|---|---|---|")
    for label in LABELS:
        print(f"| {label} | {seconds[label, 'offline']:.3f} | {seconds[label, 'online']:.3f} |")
    for label in LABELS[1:]:
        ratio = seconds[label, "online"] / seconds["state", "online"]
        print(f"\n{label} / state, online: {ratio:.1f}x")
    print()
    print("| preset | policy | offline + online updates | hours of updates |\n|---|---|---|---|")
    for name in ("quick", "paper"):
        preset = PRESETS[name]
        offline, online = pipeline_updates(preset)
        # An image preset's updates, with the image policy's own encoders or through an
        # estimator.
        labels = [label for label in LABELS if label.split()[0] == preset.policy]
        for label in labels:
            hours = (offline * seconds[label, "offline"] + online * seconds[label, "online"]) / 3600
            print(f"| {name} | {label} | {offline:,} + {online:,} | {hours:.1f} |")


if __name__ == "__main__":
    typer.run(main)
