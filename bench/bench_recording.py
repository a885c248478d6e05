"""Recording at a real cell's rates, against the emulator.

The emulator serves a UR5e (servo 500 Hz) with two 640x480 cameras at 30 fps; the
host runs the robot loop at 10 Hz with a small end-effector wave as its action source,
three ways, one after another on the same arm: the loop alone; the loop recording live
episodes (every camera frame and every controller package, :mod:`twinrl_data.streams`)
for ``--duration`` seconds in episodes of ``--episode-seconds``; the loop recording with
the live view saved to an .rrd. ``--rounds N`` takes the three ways in turn N times
(the recording's seconds split between the rounds), so that a drift of the machine
falls on all three alike, and reports each round's p99 beside the pooled one. It
reports the frames and samples delivered and
written (dropped = delivered, not written), the packages the emulator itself did not
send in time (gaps in the controller's clock: the emulator's, not the recorder's), the
recorder's share of one core (its threads' CPU over the recording's wall time), the
whole host process's share, the loop's period p50/p99 each way, and the LeRobot export
of the first recorded episode against lerobot's own loop on the same frames, side by
side: at the cameras' rate (every frame a row, the frames encoded while recording copied
into the videos, what ``twinrl data export`` does with a live episode) and at the control
rate (one frame per step, encoded at export). ``--pin`` puts the emulator on one core
and the host on the others, as a controller of its own would leave the host's processor
to the host (on two cores the emulator then serves less of the real rates).
``--realtime-priority N`` gives the cell that ``arm.realtime_priority`` (the loop's
thread at SCHED_FIFO N; needs root or an rtprio limit). Usage::

    MUJOCO_GL=egl python bench/bench_recording.py --duration 600
    MUJOCO_GL=egl python bench/bench_recording.py --duration 120 --pin
    MUJOCO_GL=egl python bench/bench_recording.py --duration 180 --rounds 3 --pin
    MUJOCO_GL=egl python bench/bench_recording.py --duration 180 --rounds 3 --pin \
        --realtime-priority 50
    MUJOCO_GL=egl python bench/bench_recording.py --duration 20 --episode-seconds 10
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
import yaml
from bench_data import lerobot_loop  # the same loop the data benchmark measures against

from twinrl_data.console import quiet_encoders
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.live_export import read_live
from twinrl_data.live_video import decode_frame
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import EpisodeFolder, Recorder
from twinrl_data.streams import read_samples
from twinrl_robot.backends import open_robot
from twinrl_robot.live_view import LiveView
from twinrl_robot.loop import run_episode
from twinrl_robot.ur.emulator.harness import EmulatorProcess
from twinrl_sim.tasks import Task, TaskConfig, make_task

HOST = "127.0.0.9"
CAMERAS = ("front", "wrist")
CONTROL_HZ, SERVO_HZ, FPS = 10, 500, 30


class Wave:
    """A slow circle of the TCP (1 cm a step at most), the gripper still."""

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.t = 0

    def act(self, observation: dict) -> np.ndarray:
        self.t += 1
        self.observation = observation
        phase = 2 * np.pi * self.t / 40
        return np.array([0.01 * np.cos(phase), 0.01 * np.sin(phase), 0, 0, 0, 0, 0], np.float32)

    def interrupted(self) -> None:
        pass


@dataclass
class Tally:
    """What the recorded episodes delivered, wrote and cost, summed over them."""

    paths: list[Path] = field(default_factory=list)
    periods: list[list[float]] = field(default_factory=list)  # the loop's, one list a round
    delivered: int = 0  # camera frames the cameras handed over
    written: int = 0  # camera frames in the episodes
    received: int = 0  # controller packages received
    samples: int = 0  # controller samples in the episodes
    cpu: float = 0.0  # s of the recorder's threads
    process_cpu: float = 0.0  # s of the whole host process while recording
    wall: float = 0.0  # s of recording
    backlog: int = 0  # the recorder's most items waiting

    def add(self, result, wall: float, backend, recorder: Recorder) -> None:
        """One recorded episode of the current round, ``wall`` s long."""
        self.paths.append(result.path)
        self.periods[-1] += result.periods
        self.wall += wall
        sensors, live = backend.sensors, recorder.saved_live
        self.delivered += sum(sensors.handed.values())
        self.received += sensors.received
        self.written += sum(live.counts[c] for c in CAMERAS)
        self.samples += live.counts["controller"]
        self.cpu += sensors.cpu + live.cpu
        self.backlog = max(self.backlog, live.backlog)


def write_cell(folder: Path, realtime_priority: int | None) -> Path:
    cameras = [
        {"name": name, "kind": "opencv", "source": f"http://{HOST}:8080/{name}",
         "width": 640, "height": 480, "fps": FPS}
        for name in CAMERAS
    ]  # fmt: skip
    cell = {
        "name": "real_rates",
        "twin": "pick_place",
        "arm": {
            "model": "ur5e",
            "host": HOST,
            "control_hz": CONTROL_HZ,
            "servo_hz": SERVO_HZ,
            "realtime_priority": realtime_priority,
        },
        "gripper": {"kind": "robotiq_2f85"},
        "cameras": cameras,
        "safety": {"max_step_translation": 0.05},
    }
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(cell))
    return path


def percentiles(rounds: list[list[float]]) -> str:
    """p50 / p99 / max (ms) of the periods of every round, then each round's p99 where
    there are several."""
    ms = 1000 * np.concatenate(rounds)
    pooled = f"{np.percentile(ms, 50):.1f} / {np.percentile(ms, 99):.1f} / {ms.max():.1f}"
    if len(rounds) == 1:
        return pooled
    each = ", ".join(f"{np.percentile(1000 * np.asarray(r), 99):.1f}" for r in rounds)
    return f"{pooled} (p99 by round: {each})"


def main(
    duration: Annotated[float, typer.Option(help="Seconds of recording.")] = 600.0,
    episode_seconds: Annotated[float, typer.Option(help="Seconds per episode.")] = 60.0,
    compare_seconds: Annotated[
        float, typer.Option(help="Seconds of the loop alone and with the live view.")
    ] = 60.0,
    pin: Annotated[
        bool,
        typer.Option(
            help="The emulator on one core, this process on the others (Linux): a "
            "controller of its own leaves the host's processor to the host."
        ),
    ] = False,
    realtime_priority: Annotated[
        int,
        typer.Option(
            help="The cell's arm.realtime_priority: SCHED_FIFO for the loop's thread (0: "
            "the normal policy)."
        ),
    ] = 0,
    rounds: Annotated[
        int,
        typer.Option(
            min=1,
            help="Times the loop alone, recording and with the live view are taken in "
            "turn; the recording's seconds are split between them.",
        ),
    ] = 1,
) -> None:
    quiet_encoders()
    cores = sorted(os.sched_getaffinity(0))
    if pin and len(cores) < 2:
        raise typer.BadParameter("needs two cores or more", param_hint="--pin")
    work = Path(tempfile.mkdtemp(prefix="twinrl-bench-recording-"))
    cell = write_cell(work, realtime_priority or None)
    task = make_task("pick_place")
    config = task.sample_config(np.random.default_rng(0), "ID")
    rows: list[tuple[str, str]] = []
    try:
        with EmulatorProcess(cell) as emulator:
            if pin:  # every thread of each; those started later inherit their starter's
                _pin(emulator.process.pid, cores[-1:])
                _pin(os.getpid(), cores[:-1])
            robot = open_robot(
                "real", task, cameras=CAMERAS, effort=True, object_poses=False,
                cell=cell, emulated=True,
            )  # fmt: skip
            names = robot.names

            def meta():
                return task.episode_meta(source="teleop", world="real", names=names, config=config)

            steps = lambda seconds: max(2, round(seconds * CONTROL_HZ))  # noqa: E731
            alone: list[list[float]] = []
            viewed: list[list[float]] = []
            tally = Tally()
            try:
                recorder = Recorder(EpisodeFolder(work / "episodes"))
                backend = _backend(robot)
                for turn in range(rounds):
                    alone.append(
                        run_episode(
                            robot, Wave(), task, config, judge=None,
                            max_steps=steps(compare_seconds),
                        ).periods
                    )  # fmt: skip
                    tally.periods.append([])
                    left = duration / rounds
                    process_started = time.process_time()
                    while left > 0:
                        seconds = min(episode_seconds, left)
                        left -= seconds
                        started = time.perf_counter()
                        result = run_episode(
                            robot, Wave(), task, config, judge=None, max_steps=steps(seconds),
                            recorder=recorder, meta=meta(),
                        )  # fmt: skip
                        tally.add(result, time.perf_counter() - started, backend, recorder)
                    tally.process_cpu += time.process_time() - process_started
                    view = LiveView(
                        str(work / f"live-{turn}.rrd"), task, CAMERAS, names["observation.state"]
                    )
                    wave = Wave()
                    viewed.append(
                        run_episode(
                            robot, wave, task, config, judge=None,
                            max_steps=steps(compare_seconds),
                            recorder=Recorder(EpisodeFolder(work / f"viewed-{turn}")),
                            meta=meta(),
                            on_step=lambda t, sent, view=view, wave=wave: view.step(
                                wave.observation, sent
                            ),
                        ).periods
                    )  # fmt: skip
                    view.close()
            finally:
                robot.close()
        paths = tally.paths
        gaps = 0
        for path in paths:
            clock = read_samples(path)["controller"].clock
            gaps += int(np.sum(np.round(np.diff(clock) * SERVO_HZ) - 1))
        first = read_live(paths[0])  # the rows' frames in memory, for lerobot's own loop
        images = {c: np.stack([decode_frame(j) for j in f]) for c, f in first.frames.items()}
        own_live = lerobot_loop([replace(first.episode, images=images)], work / "own_live")
        del first, images
        start = time.perf_counter()
        export_dataset([read_live(paths[0])], work / "ours_live")
        ours_live = time.perf_counter() - start
        own_steps = lerobot_loop([read_episode(paths[0])], work / "own_steps")
        start = time.perf_counter()
        export_dataset([read_episode(paths[0])], work / "ours_steps")
        ours_steps = time.perf_counter() - start
    finally:
        shutil.rmtree(work, ignore_errors=True)
    rows += [
        ("camera frames: delivered / written / dropped", f"{tally.delivered} / "
         f"{tally.written} / {tally.delivered - tally.written}"),
        ("controller samples: received / written / dropped", f"{tally.received} / "
         f"{tally.samples} / {tally.received - tally.samples}"),
        ("controller packages the emulator did not send in time", f"{gaps}"),
        ("recorder's share of one core (its threads)", f"{100 * tally.cpu / tally.wall:.1f} %"),
        ("host process's share of one core (cameras' decoding, loop, recorder)",
         f"{100 * tally.process_cpu / tally.wall:.1f} %"),
        ("recorder's most items waiting", f"{tally.backlog}"),
        ("loop period p50 / p99 / max (ms), loop alone", percentiles(alone)),
        ("loop period p50 / p99 / max (ms), recording", percentiles(tally.periods)),
        ("loop period p50 / p99 / max (ms), recording + live view", percentiles(viewed)),
        ("export of the first episode at the cameras' rate: twinrl / lerobot's own loop (s)",
         f"{ours_live / own_live:.2f} ({ours_live:.1f} / {own_live:.1f})"),
        ("export of the first episode at the control rate: twinrl / lerobot's own loop (s)",
         f"{ours_steps / own_steps:.2f} ({ours_steps:.1f} / {own_steps:.1f})"),
    ]  # fmt: skip
    pinned = f"; the emulator on core {cores[-1]}, the host on the rest" if pin else ""
    turns = f", in {rounds} rounds" if rounds > 1 else ""
    if realtime_priority:
        pinned += f"; the loop's thread at SCHED_FIFO {realtime_priority}"
    print(f"{duration:g} s recorded in {len(paths)} episodes{turns}: 2 cameras 640x480 at "
          f"{FPS} fps, controller at {SERVO_HZ} Hz, loop at {CONTROL_HZ} Hz{pinned}\n")  # fmt: skip
    print("| what | figure |\n|---|---|")
    for name, figure in rows:
        print(f"| {name} | {figure} |")


def _pin(pid: int, cores: list[int]) -> None:
    """Every thread of process ``pid`` onto ``cores`` (Linux)."""
    for thread in Path(f"/proc/{pid}/task").iterdir():
        os.sched_setaffinity(int(thread.name), cores)


def _backend(robot):
    from twinrl_robot.wrappers.base import layers

    return list(layers(robot))[-1]


if __name__ == "__main__":
    typer.run(main)
