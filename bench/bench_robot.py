"""The UR driver against the emulator, at a CB3's 125 Hz and an e-Series' 500 Hz servo
rate, measured side by side in one run:

- **command to observation**: the servo stream steps its target by 5 mrad on every joint
  and the receive interface is polled until the controller reports the new target
  (``target_q``: one servo period to send, one RTDE period back: the command path) and
  until the measured joints have moved 1 mrad toward it (the arm's response as well);
- **servo period**: the interval between consecutive servoJ targets while a 10 Hz episode
  of small random actions runs (p50 / p99 / max; the ideal is 1/servo rate);
- **CPU share**: CPU seconds per wall second of the driver during that episode (the
  host's process, and the child that holds ur_rtde and the servo thread), and of the
  emulator's.

The emulator runs in its own process, as it must (ur_rtde holds the interpreter while it
waits); on this 2-core machine all three share the cores. Usage::

    python bench/bench_robot.py --seconds 5 --out bench/results/robot.json
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
import yaml

from twinrl_robot.cell_file import load_cell
from twinrl_robot.ur.driver import URArm
from twinrl_robot.ur.emulator import free_loopback_host
from twinrl_robot.ur.emulator.harness import EmulatorProcess
from twinrl_sim.tasks import make_task

STEP = 5e-3  # rad: the latency probe's target step
MOVED = 1e-3  # rad: how far the joints must move to count as a response


def cpu_seconds(pid: int | str = "self") -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def latency(arm: URArm, trials: int) -> tuple[list[float], list[float]]:
    """Per trial: seconds until the controller echoes the step, and until the arm moves."""
    echoes, responses = [], []
    for _ in range(trials):
        arm.stream.hold(arm.measured_q())
        time.sleep(0.2)
        start = arm.measured_q()
        began = time.perf_counter()
        arm.stream.hold(start + STEP)
        echo = None
        while np.abs(arm.measured_q() - start).max() < MOVED:
            if echo is None and np.abs(arm.controller_target_q() - start).max() > STEP / 2:
                echo = time.perf_counter() - began
            if time.perf_counter() - began > 1.0:
                raise RuntimeError("the arm did not respond within 1 s")
        responses.append(time.perf_counter() - began)
        echoes.append(echo if echo is not None else responses[-1])
    return echoes, responses


def measure(servo_hz: float, seconds: float, trials: int, folder: Path) -> dict:
    cell_file = folder / f"cell_{servo_hz:g}.yaml"
    cell_file.write_text(
        yaml.safe_dump(
            {
                "name": "bench",
                "twin": "pick_place",
                "arm": {"host": free_loopback_host(), "servo_hz": servo_hz},
            }
        )
    )
    task = make_task("pick_place")
    with EmulatorProcess(cell_file, effects=None) as emulator:
        assert emulator.process is not None
        arm = URArm(load_cell(cell_file), task, effort=True)
        try:
            arm.reset(task.sample_config(np.random.default_rng(0)))
            echoes, responses = latency(arm, trials)
            rng = np.random.default_rng(0)
            link = arm._link.pid
            sent_before = len(arm.stream.periods)
            driver_cpu = cpu_seconds() + cpu_seconds(link)
            emulator_cpu = cpu_seconds(emulator.process.pid)
            began = time.perf_counter()
            while time.perf_counter() - began < seconds:
                action = np.zeros(7, np.float32)
                action[:3] = rng.uniform(-0.004, 0.004, 3)
                arm.act(action)
                arm.observe()
            wall = time.perf_counter() - began
            driver_share = (cpu_seconds() + cpu_seconds(link) - driver_cpu) / wall
            emulator_share = (cpu_seconds(emulator.process.pid) - emulator_cpu) / wall
            periods = np.array(arm.stream.periods[sent_before + 1 :]) * 1000.0
        finally:
            arm.close()
    echo_ms, response_ms = np.array(echoes) * 1000.0, np.array(responses) * 1000.0
    return {
        "servo_hz": servo_hz,
        "echo_ms_p50": float(np.percentile(echo_ms, 50)),
        "echo_ms_p99": float(np.percentile(echo_ms, 99)),
        "response_ms_p50": float(np.percentile(response_ms, 50)),
        "response_ms_p99": float(np.percentile(response_ms, 99)),
        "period_ms_p50": float(np.percentile(periods, 50)),
        "period_ms_p99": float(np.percentile(periods, 99)),
        "period_ms_max": float(periods.max()),
        "driver_cpu_share": driver_share,
        "emulator_cpu_share": emulator_share,
    }


def main(
    seconds: Annotated[float, typer.Option(help="Seconds of episode per rate.")] = 5.0,
    trials: Annotated[int, typer.Option(help="Latency probes per rate.")] = 20,
    out: Annotated[Path | None, typer.Option(help="Write the figures as JSON here.")] = None,
) -> None:
    with tempfile.TemporaryDirectory() as folder:
        rows = [measure(hz, seconds, trials, Path(folder)) for hz in (125.0, 500.0)]
    print(
        "| servo rate | command echoed p50 / p99 | arm moved p50 / p99 | "
        "servo period p50 / p99 / max | driver CPU | emulator CPU |"
    )
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['servo_hz']:g} Hz | {r['echo_ms_p50']:.1f} / {r['echo_ms_p99']:.1f} ms "
            f"| {r['response_ms_p50']:.1f} / {r['response_ms_p99']:.1f} ms "
            f"| {r['period_ms_p50']:.2f} / {r['period_ms_p99']:.2f} / {r['period_ms_max']:.2f} ms "
            f"| {100 * r['driver_cpu_share']:.0f} % | {100 * r['emulator_cpu_share']:.0f} % |"
        )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    typer.run(main)
