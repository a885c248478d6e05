"""Twin demo synthesis speed: N demonstrations end to end, with both cameras rendered
and, side by side, without cameras (the demos a state policy learns from).

The paper builds a twin demo set in about a minute; the target here is 90 demos with
cameras in at most 2 minutes on 2 cores (synthesis in worker processes, then LeRobot
export). Usage::

    python bench/bench_expand.py --task insert_hexagon --demos 90
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Annotated

import typer

from twinrl_sim.expand import ExpandReport, expand


def timed_expand(task: str, demos: int, workers: int, images: bool) -> tuple[ExpandReport, float]:
    out = Path(tempfile.mkdtemp(prefix="twinrl-expand-")) / "run"
    start = time.perf_counter()
    report = expand(
        task,
        id_count=demos // 2,
        ood_count=demos - demos // 2,
        out=out,
        workers=workers,
        images=images,
    )
    total = time.perf_counter() - start
    shutil.rmtree(out.parent)
    return report, total


def main(
    task: Annotated[str, typer.Option(help="Task to synthesize.")] = "insert_hexagon",
    demos: Annotated[
        int, typer.Option(help="Demonstrations, split evenly between ID and OOD.")
    ] = 90,
    workers: Annotated[int, typer.Option(help="Worker processes.")] = 2,
) -> None:
    os.environ.setdefault("SVT_LOG", "1")
    import datasets

    datasets.disable_progress_bars()
    cameras, with_total = timed_expand(task, demos, workers, images=True)
    states, without_total = timed_expand(task, demos, workers, images=False)
    assert states.kept == cameras.kept, "the same seed must give the same demonstrations"
    kept = sum(cameras.kept.values())
    attempts = sum(cameras.attempts.values())
    print(f"{task}: {kept} demos from {attempts} attempts, {workers} workers\n")
    print("| what | 2 cameras, 128x128 (s) | no cameras (s) |\n|---|---|---|")
    print(
        "| synthesis (plan + execute + record) "
        f"| {cameras.seconds_synthesis:.1f} | {states.seconds_synthesis:.1f} |"
    )
    print(f"| LeRobot export | {cameras.seconds_export:.1f} | {states.seconds_export:.1f} |")
    print(f"| end to end | {with_total:.1f} | {without_total:.1f} |")
    print(
        f"\nper demo with cameras: {with_total / max(kept, 1):.2f} s; target for 90 demos: "
        f"120 s; without cameras {with_total / without_total:.1f}x faster"
    )


if __name__ == "__main__":
    typer.run(main)
