"""The RL update's cost by policy kind, side by side, and what it makes of each preset.

Twin and real RL make one gradient update per environment step (``utd``), and on CPU
the updates, not the simulation, set how long a pipeline takes. This times the TwinRL
agent's update (critic ensemble + actor, batch 64, chunks as SFT makes them) for the
state policy, the image policy with its own encoders and the image policy acting through
a pose estimator (whose estimates the replay buffer computes once per episode) on the
same few twin demos, offline (with the Cal-QL regulariser) and online, prints their
ratios, and multiplies each by the number of
updates a preset's pipeline makes (Stage II, then four methods x seeds of real RL, each
with its offline phase). ``--device`` (repeatable) times each device side by side in
one run, e.g. the CPU and a GPU (bfloat16 autocast there). The updates cycle through a
few batches sampled beforehand (sampling, on the CPU, is timed apart and added to each
update in the presets' hours). ``--prepare-only DIR`` writes the demos, checkpoints and
batches, and ``--prepared DIR`` times them, on a machine without the simulator. Usage::

    python bench/bench_rl_update.py --updates 20
    python bench/bench_rl_update.py --updates 50 --device cpu --device cuda
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import typer

from twinrl_data.atomic import write_text_atomic
from twinrl_data.console import quiet_encoders
from twinrl_learn.agent import Agent
from twinrl_learn.compute import resolve_device
from twinrl_learn.perception import train_estimator
from twinrl_learn.policy import Policy
from twinrl_learn.replay import ReplayBuffer, TransitionBatch
from twinrl_learn.settings import PerceptionSettings, RLConfig, SFTConfig
from twinrl_learn.sft import train_sft
from twinrl_learn.studies.presets import (
    METHOD_TABLE,
    PRESETS,
    Preset,
    real_rl_config,
    twin_rl_config,
)

LABELS = ("state", "vla", "vla through an estimator")
BATCHES = 4  # sampled batches per policy kind that the timed updates cycle through
PREPARED = "prepared.json"


def prepare(root: Path, demos: int, samples: int = 20) -> None:
    """Twin demos, a checkpoint per policy kind, and per kind :data:`BATCHES` sampled
    batches saved beside it with the mean time a sample takes (on the CPU): everything
    the timing needs, so that it can run on a machine without the simulator."""
    from twinrl_sim.expand import expand  # here: the timing alone needs no simulator

    report = expand("pick_place", id_count=demos // 2, ood_count=demos - demos // 2,
                    out=root / "demos", workers=1)  # fmt: skip
    estimator = root / "estimator"
    train_estimator(PerceptionSettings(datasets=[report.dataset], out=str(estimator),
                                       steps=1, device="cpu"))  # fmt: skip
    sampling = {}
    for label in LABELS:
        kind, folder = label.split()[0], root / label.replace(" ", "_")
        perception = str(estimator) if "estimator" in label else None
        train_sft(SFTConfig(datasets=[report.dataset], out=str(folder / "checkpoint"),
                            policy=kind, steps=1, perception=perception,
                            device="cpu"))  # fmt: skip
        policy = Policy.from_pretrained(folder / "checkpoint")
        buffer = ReplayBuffer.from_datasets([report.dataset], **policy.replay_views())
        config, rng = RLConfig(), np.random.default_rng(0)

        def batch(buffer=buffer, chunk=policy.config.chunk, config=config, rng=rng):
            return buffer.sample(config.batch_size, rng, chunk=chunk, gamma=config.gamma)

        batch()  # the estimates, computed once per episode, before the timing
        start = time.perf_counter()
        for _ in range(samples):
            batch()
        sampling[label] = (time.perf_counter() - start) / samples
        for i in range(BATCHES):
            sampled = batch()
            if sampled.estimates is not None:  # what the update reads in place of images
                sampled = replace(sampled, images={}, next_images={})
            save_batch(sampled, folder / f"batch{i}.npz")
    write_text_atomic(root / PREPARED, json.dumps({"sample_seconds": sampling}, indent=1))


def save_batch(batch: TransitionBatch, path: Path) -> None:
    """A sampled batch as one compressed .npz (no pickles)."""
    arrays = {}
    for item in fields(batch):
        value = getattr(batch, item.name)
        if isinstance(value, dict):
            arrays |= {f"{item.name}.{key}": array for key, array in value.items()}
        elif value is not None:
            arrays[item.name] = np.asarray(value)
    np.savez_compressed(path, **arrays)


def load_batch(path: Path) -> TransitionBatch:
    with np.load(path) as saved:
        arrays = {key: saved[key] for key in saved.files}
    values = {}
    for item in fields(TransitionBatch):
        prefix = f"{item.name}."
        if item.name in ("images", "next_images"):
            values[item.name] = {
                key.removeprefix(prefix): array
                for key, array in arrays.items()
                if key.startswith(prefix)
            }
        elif item.name == "instruction":
            values[item.name] = [str(text) for text in arrays[item.name]]
        else:
            values[item.name] = arrays.get(item.name)
    return TransitionBatch(**values)


def seconds_per_update(
    checkpoint: Path, batches: list[TransitionBatch], updates: int, offline: bool,
    device: torch.device,
) -> float:  # fmt: skip
    """Mean wall time of one TwinRL update on ``batches`` in turn: an offline one (with
    the Cal-QL regulariser) or an online one, from the checkpoint afresh, on ``device``."""
    policy = Policy.from_pretrained(checkpoint, device)
    config = RLConfig.for_method("twinrl", seed=0, offline_steps=updates + 1 if offline else 0)
    agent = Agent(policy, config)
    for i in range(3):  # warm-up: first-call allocations, a GPU's kernel choices
        agent.update(batches[i % len(batches)])
    synchronize(device)
    start = time.perf_counter()
    for i in range(updates):
        agent.update(batches[i % len(batches)])
    synchronize(device)
    return (time.perf_counter() - start) / updates


def synchronize(device: torch.device) -> None:
    """Wait for a GPU's queued work, so that a timing holds all of it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


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
    device: Annotated[
        list[str] | None, typer.Option(help="cpu, cuda or auto; repeat to compare.")
    ] = None,
    prepare_only: Annotated[
        Path | None,
        typer.Option(help="Only write the demos, checkpoints and batches into this folder."),
    ] = None,
    prepared: Annotated[
        Path | None,
        typer.Option(help="Time the updates on a folder --prepare-only wrote (no simulator)."),
    ] = None,
) -> None:
    devices = [resolve_device(name) for name in device or ["cpu"]]
    quiet_encoders()
    torch.set_num_threads(2)
    if prepare_only is not None:
        prepare(prepare_only, demos)
        return
    root = prepared or Path(tempfile.mkdtemp(prefix="twinrl-rl-update-"))
    try:
        if prepared is None:
            prepare(root, demos)
        sampling = json.loads((root / PREPARED).read_text())["sample_seconds"]
        seconds = {}
        for label in LABELS:
            folder = root / label.replace(" ", "_")
            batches = [load_batch(folder / f"batch{i}.npz") for i in range(BATCHES)]
            for on in devices:
                for phase in ("offline", "online"):
                    seconds[label, on.type, phase] = seconds_per_update(
                        folder / "checkpoint", batches, updates, phase == "offline", on
                    )
    finally:
        if prepared is None:
            shutil.rmtree(root)
    report(seconds, sampling, devices, updates)


def report(
    seconds: dict[tuple[str, str, str], float],
    sampling: dict[str, float],
    devices: list[torch.device],
    updates: int,
) -> None:
    """The tables: seconds per update by kind and device, ratios, and each preset's hours
    of updates (each update with its batch's sampling, on the CPU)."""
    batch = RLConfig().batch_size
    print(f"TwinRL update, batch {batch}, {torch.get_num_threads()} CPU threads, mean of {updates}")
    for on in devices:
        if on.type == "cuda":
            print(f"GPU: {torch.cuda.get_device_name(on)} (bfloat16 autocast)")
    print("\n| policy | device | offline s / update | online s / update | sampling s |")
    print("|---|---|---|---|---|")
    for label in LABELS:
        for on in devices:
            offline, online = seconds[label, on.type, "offline"], seconds[label, on.type, "online"]
            print(f"| {label} | {on.type} | {offline:.4f} | {online:.4f} | {sampling[label]:.4f} |")
    for on in devices:
        for label in LABELS[1:]:
            ratio = seconds[label, on.type, "online"] / seconds["state", on.type, "online"]
            print(f"\n{label} / state, online, {on.type}: {ratio:.1f}x")
    if len(devices) > 1:
        for label in LABELS:
            first, other = (seconds[label, on.type, "online"] for on in devices[:2])
            print(f"\n{label}, online, {devices[0].type} / {devices[1].type}: {first / other:.1f}x")
    print("\n| preset | policy | device | offline + online updates | hours (update + sampling) |")
    print("|---|---|---|---|---|")
    for name in ("quick", "paper"):
        preset = PRESETS[name]
        offline, online = pipeline_updates(preset)
        # An image preset's updates, with the image policy's own encoders or through an
        # estimator.
        labels = [label for label in LABELS if label.split()[0] == preset.policy]
        for label in labels:
            for on in devices:
                hours = (
                    offline * (seconds[label, on.type, "offline"] + sampling[label])
                    + online * (seconds[label, on.type, "online"] + sampling[label])
                ) / 3600
                print(f"| {name} | {label} | {on.type} | {offline:,} + {online:,} | {hours:.1f} |")


if __name__ == "__main__":
    typer.run(main)
