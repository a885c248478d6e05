"""Twin demo synthesis speed: N demonstrations with both cameras rendered, end to end.

The paper builds a twin demo set in about a minute; the target here is 90 demos in at
most 2 minutes on 2 cores (synthesis in worker processes, then LeRobot export).
Usage::

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

from twinrl_sim.expand import expand


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
    out = Path(tempfile.mkdtemp(prefix="twinrl-expand-")) / "run"
    start = time.perf_counter()
    report = expand(
        task, id_count=demos // 2, ood_count=demos - demos // 2, out=out, workers=workers
    )
    total = time.perf_counter() - start
    shutil.rmtree(out.parent)
    kept = sum(report.kept.values())
    attempts = sum(report.attempts.values())
    print(
        f"{task}: {kept} demos (2 cameras, 128x128) from {attempts} attempts, {workers} workers\n"
    )
    print("| what | seconds |\n|---|---|")
    print(f"| synthesis (plan + execute + record) | {report.seconds_synthesis:.1f} |")
    print(f"| LeRobot export | {report.seconds_export:.1f} |")
    print(f"| end to end | {total:.1f} |")
    print(f"\nper demo: {total / max(kept, 1):.2f} s; target for 90 demos: 120 s")


if __name__ == "__main__":
    typer.run(main)
