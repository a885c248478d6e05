"""Episode-log throughput, measured side by side in one run.

- Recording: a 2-camera (128x128) episode stream into MCAP; steps/s, how many times
  real time that is at 10 Hz and 30 Hz, and the share of one core the writer needs.
- Export to LeRobot: twinrl's export from MCAP episodes next to lerobot's own
  ``create``/``add_frame``/``save_episode``/``finalize`` loop on the same frames held in
  memory; seconds of work per second of episode, and the ratio.
- Import: a LeRobotDataset back into episodes, with and without decoding the videos.
- Catalog: a filtered query over 10 000 synthetic episode rows.
- The Rerun view: seconds and megabytes to save a 60-s, 10 Hz episode with both cameras
  as an .rrd, with and without the cell in 3D, and with the cell and the twin's ghost
  (``twinrl view --save``, ``--replay``), each the median of 15 saves.

Camera frames are real twin renders (cycled), so compression sees realistic images.
Usage::

    python bench/bench_data.py --episodes 4 --steps 100
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import typer

from twinrl_data.catalog import query
from twinrl_data.lerobot_io import (
    WRITE_OPTIONS,
    export_dataset,
    features_for,
    iter_dataset_episodes,
)
from twinrl_data.mcap_log import EpisodeWriter, read_episode
from twinrl_data.schema import EpisodeMeta
from twinrl_sim.env import TwinEnv


def rendered_steps(count: int) -> tuple[list[dict], dict, dict]:
    """Contract steps with real front/wrist renders from an expert episode of the twin,
    the contract's names and the episode's task configuration."""
    env = TwinEnv("pick_place", images=True)
    obs, _ = env.reset(seed=0, options={"region": "ID"})
    expert = env.task.expert(env.config, np.random.default_rng(0))
    steps = []
    for t in range(count):
        action = expert.act(obs)
        next_obs, reward, terminated, _, info = env.step(action)
        steps.append(
            {
                **obs,
                "action": action,
                "command.joint_target": info["command.joint_target"],
                "intervention": False,
                "next.reward": reward,
                "next.done": terminated or t == count - 1,
                "next.success": terminated,
            }
        )
        obs = next_obs
    names = {
        "observation.state": env.cell.state_names,
        "observation.environment_state": env.cell.environment_names,
    }
    config = env.config.to_dict()
    env.close()
    return steps, names, config


def record(path: Path, steps: list[dict], meta: EpisodeMeta) -> tuple[float, float]:
    """Wall and CPU seconds to write ``steps`` as one episode."""
    wall, cpu = time.perf_counter(), time.process_time()
    with EpisodeWriter(path, meta) as log:
        for step in steps:
            log.append(step)
    return time.perf_counter() - wall, time.process_time() - cpu


def lerobot_loop(episodes, root: Path) -> float:
    """lerobot's own recording path on in-memory frames (what our export must match), at
    the episodes' rate."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    start = time.perf_counter()
    dataset = LeRobotDataset.create(
        "bench/own",
        fps=round(episodes[0].meta.fps),
        features=features_for(episodes[0]),
        root=root,
        robot_type="ur5e",
        **WRITE_OPTIONS,
    )
    for episode in episodes:
        for t in range(len(episode)):
            frame = {"task": episode.meta.instruction}
            for key, values in episode.data.items():
                value = values[t]
                frame[key] = (
                    value.astype(np.float32) if value.ndim else np.array([value], value.dtype)
                )
            for camera, frames in episode.images.items():
                frame[f"observation.images.{camera}"] = frames[t]
            dataset.add_frame(frame)
        dataset.save_episode()
    dataset.finalize()
    return time.perf_counter() - start


def view_costs(
    frames: list[dict], meta: EpisodeMeta, steps: int, work: Path, repeats: int = 15
) -> tuple[dict[str, tuple[float, float]], float]:
    """Seconds and megabytes of ``twinrl view --save`` on one episode of ``steps``
    (the rendered frames cycled), without and with the cell in 3D, and with the cell and
    the twin's ghost (``--replay``: the replay's simulation included); and the seconds
    of that simulation alone. Each figure is the median of ``repeats`` saves, the
    variants taking turns, since one save's noise on a shared host is larger than the
    cell's share."""
    from twinrl_data.view import save_rrd
    from twinrl_sim.cli.view import twin_cell
    from twinrl_sim.replay import replayed_episode

    path = work / "view.mcap"
    record(path, [frames[t % len(frames)] for t in range(steps)], meta)
    episode = read_episode(path)
    cell = twin_cell(episode)
    variants = {
        "cameras and plots": None,
        "with the cell in 3D": cell,
        "with the cell and the twin's ghost": cell,
    }
    walls: dict[str, list[float]] = {label: [] for label in variants}
    sizes: dict[str, float] = {}
    replays = []
    for _ in range(repeats):
        for i, (label, shown) in enumerate(variants.items()):
            rrd = work / f"view_{i}.rrd"
            start = time.perf_counter()
            ghost = [replayed_episode(episode)] if "ghost" in label else []
            if ghost:
                replays.append(time.perf_counter() - start)
            save_rrd([episode, *ghost], rrd, cell=shown, force=True)
            walls[label].append(time.perf_counter() - start)
            sizes[label] = rrd.stat().st_size / 1e6
    out = {label: (float(np.median(walls[label])), sizes[label]) for label in variants}
    return out, float(np.median(replays))


def synthetic_catalog(path: Path, rows: int) -> None:
    rng = np.random.default_rng(0)
    table = pa.table(
        {
            "episode_key": [f"mcap:/x/{i}.mcap" for i in range(rows)],
            "task": rng.choice(
                ["pick_place", "insert_hexagon", "insert_triple_column", "erase_whiteboard"], rows
            ),
            "source": rng.choice(["teleop", "twin_demo", "twin_rl", "real_rl", "eval"], rows),
            "world": rng.choice(["real", "twin", "plant"], rows),
            "region": rng.choice(["ID", "OOD"], rows),
            "success": rng.random(rows) < 0.6,
            "length": rng.integers(20, 120, rows),
            "return": rng.normal(3, 4, rows),
            "num_interventions": rng.integers(0, 5, rows),
            "created_at": [f"2026-11-{1 + i % 28:02d}T00:00:{i % 60:02d}" for i in range(rows)],
            "config_target_1": rng.uniform(-0.4, 0.4, rows),
        }
    )
    pq.write_table(table, path)


def main(
    episodes: Annotated[int, typer.Option(help="Episodes to record and export.")] = 4,
    steps: Annotated[int, typer.Option(help="Steps per episode (10 Hz).")] = 100,
    catalog_rows: Annotated[int, typer.Option(help="Rows of the synthetic catalog.")] = 10_000,
    view_steps: Annotated[int, typer.Option(help="Steps of the episode the view saves.")] = 600,
) -> None:
    os.environ.setdefault("SVT_LOG", "1")
    import datasets

    datasets.disable_progress_bars()
    work = Path(tempfile.mkdtemp(prefix="twinrl-bench-"))
    frames, names, config = rendered_steps(steps)
    metas = [
        EpisodeMeta(
            task="pick_place",
            instruction="put the banana on the plate",
            source="twin_demo",
            world="twin",
            names=names,
            config=config,
        )
        for _ in range(episodes)
    ]
    wall = cpu = 0.0
    paths = []
    for i, meta in enumerate(metas):
        path = work / f"ep{i}.mcap"
        w, c = record(path, frames, meta)
        wall, cpu = wall + w, cpu + c
        paths.append(path)
    step_rate = episodes * steps / wall
    cpu_per_step = cpu / (episodes * steps)

    loaded = [read_episode(p) for p in paths]
    episode_seconds = episodes * steps / 10.0
    own = lerobot_loop(loaded, work / "own")
    start = time.perf_counter()
    export_dataset((read_episode(p) for p in paths), work / "ours")
    ours = time.perf_counter() - start
    start = time.perf_counter()
    imported = sum(len(e) for e in iter_dataset_episodes(work / "ours"))
    import_time = time.perf_counter() - start
    assert imported == episodes * steps
    start = time.perf_counter()  # what a state policy's SFT and replay buffers read
    imported = sum(len(e) for e in iter_dataset_episodes(work / "ours", cameras=[]))
    state_import_time = time.perf_counter() - start
    assert imported == episodes * steps

    synthetic_catalog(work / "catalog.parquet", catalog_rows)
    timings = []
    for _ in range(7):
        start = time.perf_counter()
        query(
            work / "catalog.parquet",
            task="pick_place",
            world="real",
            success=False,
            where="length > 50",
        )
        timings.append(time.perf_counter() - start)
    view, replay_seconds = view_costs(frames, metas[0], view_steps, work)
    shutil.rmtree(work)

    share = 100 * cpu_per_step
    rows = [
        ("recording: steps/s (each step = 2 frames + vectors)", f"{step_rate:,.0f}"),
        (
            "recording: times real time at 10 Hz / 30 Hz",
            f"{step_rate / 10:,.0f}x / {step_rate / 30:,.0f}x",
        ),
        (
            "recording: share of one core at 10 Hz / 30 Hz",
            f"{share * 10:.1f} % / {share * 30:.1f} %",
        ),
        ("export, lerobot's own loop: s per episode-second", f"{own / episode_seconds:.3f}"),
        ("export, twinrl from MCAP: s per episode-second", f"{ours / episode_seconds:.3f}"),
        ("export: twinrl / lerobot's own loop", f"{ours / own:.2f}"),
        (
            "import LeRobot -> episodes: s per episode-second",
            f"{import_time / episode_seconds:.3f}",
        ),
        (
            "import without cameras (state policies): s per episode-second",
            f"{state_import_time / episode_seconds:.4f}",
        ),
        (
            f"catalog query over {catalog_rows:,} rows (median of 7)",
            f"{1000 * np.median(timings):.1f} ms",
        ),
    ]
    seconds = view_steps / 10.0
    for label, (wall, size) in view.items():
        rows.append(
            (f"view of a {seconds:.0f}-s episode, {label}: s / MB", f"{wall:.2f} / {size:.1f}")
        )
    (plain_wall, plain_size), (cell_wall, cell_size), (ghost_wall, ghost_size) = view.values()
    for name, (wall, size), (base_wall, base_size) in (
        ("view: the cell in 3D adds (time / size)", (cell_wall, cell_size),
         (plain_wall, plain_size)),
        ("view: the ghost adds to the cell (time / size)", (ghost_wall, ghost_size),
         (cell_wall, cell_size)),
    ):  # fmt: skip
        more_time, more_size = 100 * (wall / base_wall - 1), 100 * (size / base_size - 1)
        rows.append((name, f"{more_time:+.0f} % / {more_size:+.0f} %"))
    rows.append(("view: of the ghost's time, the twin's replay (simulation): s",
                 f"{replay_seconds:.2f}"))  # fmt: skip
    print(
        f"{episodes} episodes x {steps} steps, 2 cameras 128x128 (JPEG in MCAP, AV1 in LeRobot)\n"
    )
    print("| what | figure |\n|---|---|")
    for name, figure in rows:
        print(f"| {name} | {figure} |")


if __name__ == "__main__":
    typer.run(main)
