"""The pipeline's real-RL phase, one process against worker processes, side by side.

Runs a preset's shared stages (Stage I, Stage II, mining) once, then its real-RL runs
twice from copies of them: with one process and with ``--workers`` processes. Prints
both wall times, their ratio, and whether the two reports are identical (they must be:
the runs are independent and seeded). Usage::

    python bench/bench_pipeline.py --preset smoke --workers 2
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Annotated

import torch
import typer

from twinrl_data.console import quiet_encoders
from twinrl_learn.studies.pipeline import run_demo


def main(
    preset: Annotated[str, typer.Option(help="smoke (minutes) or quick (about 40 min).")] = "smoke",
    task: Annotated[str, typer.Option(help="Task of the pipeline.")] = "pick_place",
    workers: Annotated[int, typer.Option(help="Worker processes of the parallel run.")] = 2,
) -> None:
    torch.set_num_threads(1)
    quiet_encoders()
    root = Path(tempfile.mkdtemp(prefix="twinrl-pipeline-"))
    try:
        shared = root / "shared"
        run_demo(task, preset, shared, workers=workers, log=lambda _: None)
        seconds, reports = {}, {}
        for count in (1, workers):
            folder = root / f"workers{count}"
            shutil.copytree(shared, folder, ignore=shutil.ignore_patterns("real_rl", "report*"))
            start = time.perf_counter()
            run_demo(task, preset, folder, workers=count, resume=True, log=lambda _: None)
            seconds[count] = time.perf_counter() - start
            reports[count] = json.loads((folder / "report.json").read_text())
    finally:
        shutil.rmtree(root)
    runs = len(reports[1]["methods"]) * len(reports[1]["seeds"])
    print(f"{task}, preset {preset}: real-RL phase ({runs} runs) and report\n")
    print("| processes | seconds |\n|---|---|")
    for count, value in seconds.items():
        print(f"| {count} | {value:.1f} |")
    print(f"\nspeed-up: {seconds[1] / seconds[workers]:.2f}x")
    print(f"reports identical: {reports[1] == reports[workers]}")


if __name__ == "__main__":
    typer.run(main)
