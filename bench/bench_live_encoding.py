"""The recorder at a real cell's full rates, fed in real time without an emulator.

On the 2-core machine the UR emulator cannot render two 640x480 cameras at 30 fps beside
its 500 Hz plant (``bench/bench_recording.py`` records what it does deliver), so the
recorder's share of a core at the real rates is measured here on its own: a live
episode (:class:`twinrl_data.streams.LiveEpisode`) is handed two cameras' frames at 30
fps, the controller's 500 Hz samples in batches every 0.2 s and 10 Hz control steps, on
the clock, for ``--seconds``, and its thread's CPU time is divided by the wall time.

The frames are the twin's cameras rendered at 640x480 with a camera's noise (a frame
of a flat colour encodes in nothing), the arm moving between them. Side by side in the
same run, each frame's encoding cost three ways: the log's H.264 keyframe (what the
recorder does, once per frame), and what it did before, a JPEG at quality 90 for the
log plus an H.264 frame (GOP 2, crf 30) for the export's video. Usage::

    MUJOCO_GL=egl python bench/bench_live_encoding.py --seconds 60
"""

from __future__ import annotations

import io
import tempfile
import threading
import time
from fractions import Fraction
from pathlib import Path
from typing import Annotated

import av
import cv2
import mujoco
import numpy as np
import typer

from twinrl_data.live_video import FrameEncoder
from twinrl_data.mcap_log import EpisodeWriter
from twinrl_data.schema import STATE, EpisodeMeta, step_record
from twinrl_data.streams import LiveEpisode
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.tasks import make_task

CAMERAS = ("front", "wrist")
FPS, SERVO_HZ, CONTROL_HZ = 30, 500, 10
WIDTH, HEIGHT = 640, 480


def camera_frames(count: int, seed: int = 0) -> dict[str, list[np.ndarray]]:
    """``count`` frames of each camera: the twin's pick-and-place cell rendered with the
    arm's joints swept, with a camera's noise."""
    rng = np.random.default_rng(seed)
    task = make_task("pick_place")
    cell = Cell(compile_scene(task.scene))
    task.place(cell, task.sample_config(rng))
    start = cell.data.qpos.copy()
    frames: dict[str, list[np.ndarray]] = {camera: [] for camera in CAMERAS}
    for k in range(count):
        cell.data.qpos[:6] = start[:6] + 0.15 * np.sin(2 * np.pi * k / count + np.arange(6))
        mujoco.mj_forward(cell.model, cell.data)
        for camera in CAMERAS:
            image = cell.render(camera, width=WIDTH, height=HEIGHT).astype(np.int16)
            noisy = image + rng.normal(0, 2.5, image.shape)
            frames[camera].append(np.clip(noisy, 0, 255).astype(np.uint8))
    return frames


def encoding_costs(frames: list[np.ndarray]) -> dict[str, float]:
    """ms of CPU per frame: the log's H.264 keyframe now; a JPEG and an export H.264
    frame before."""
    encoder = FrameEncoder("front")
    start = time.thread_time()
    for image in frames:
        encoder.encode(image)
    now = (time.thread_time() - start) / len(frames)
    start = time.thread_time()
    for image in frames:
        cv2.imencode(".jpg", image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    jpeg = (time.thread_time() - start) / len(frames)
    container = av.open(io.BytesIO(), "w", format="mp4")
    stream = container.add_stream(
        "h264", FPS, options={"g": "2", "crf": "30", "preset": "ultrafast", "threads": "1",
                              "x264-params": "log=-1"},
    )  # fmt: skip
    stream.pix_fmt, stream.width, stream.height = "yuv420p", WIDTH, HEIGHT
    start = time.thread_time()
    for k, image in enumerate(frames):
        frame = av.VideoFrame.from_ndarray(image, format="rgb24")
        frame.pts, frame.time_base = k, Fraction(1, FPS)
        container.mux(stream.encode(frame))
    video = (time.thread_time() - start) / len(frames)
    container.close()
    return {"now": 1e3 * now, "jpeg": 1e3 * jpeg, "video": 1e3 * video}


def record(frames: dict[str, list[np.ndarray]], seconds: float, folder: Path) -> tuple[float, int]:
    """Feed a live episode at the real rates for ``seconds``: its thread's share of a
    core, and the most items it had waiting."""
    meta = EpisodeMeta(task="pick_place", source="teleop", world="real", fps=CONTROL_HZ)
    writer = EpisodeWriter(folder / "live.mcap", meta)
    started = time.monotonic()
    live = LiveEpisode(
        writer,
        cameras=dict.fromkeys(CAMERAS, FPS),
        samples={STATE: [f"s.{i}" for i in range(20)]},
        started=started,
    )

    def cameras() -> None:
        for k in range(round(seconds * FPS)):
            due = started + k / FPS
            time.sleep(max(0.0, due - time.monotonic()))
            for camera in CAMERAS:
                live.frame(camera, frames[camera][k % len(frames[camera])], due, k)

    def controller() -> None:
        batch = SERVO_HZ // 5
        for k in range(round(seconds * 5)):
            due = started + (k + 1) / 5
            time.sleep(max(0.0, due - time.monotonic()))
            times = due - 0.2 + np.arange(batch) / SERVO_HZ
            live.samples(STATE, times, np.zeros((batch, 20), np.float32), times - started)

    threads = [threading.Thread(target=cameras), threading.Thread(target=controller)]
    for thread in threads:
        thread.start()
    for t in range(round(seconds * CONTROL_HZ)):
        due = started + t / CONTROL_HZ
        time.sleep(max(0.0, due - time.monotonic()))
        observation = {STATE: np.zeros(20, np.float32)}
        live.step(step_record(observation, np.zeros(7), np.zeros(6), 0.0, False, False), due)
    for thread in threads:
        thread.join()
    live.close()
    wall = time.monotonic() - started
    writer.close()
    return live.cpu / wall, live.backlog


def main(
    seconds: Annotated[float, typer.Option(help="Seconds recorded at the real rates.")] = 60.0,
) -> None:
    frames = camera_frames(60)
    costs = encoding_costs(frames["front"])
    with tempfile.TemporaryDirectory() as folder:
        share, backlog = record(frames, seconds, Path(folder))
    before = costs["jpeg"] + costs["video"]
    print(
        f"{seconds:g} s of 2 cameras {WIDTH}x{HEIGHT} at {FPS} fps, {SERVO_HZ} Hz samples, "
        f"{CONTROL_HZ} Hz steps, fed in real time\n\n"
        "| what | figure |\n|---|---|\n"
        f"| recorder's share of one core (its thread) | {100 * share:.1f} % |\n"
        f"| recorder's most items waiting | {backlog} |\n"
        f"| a frame's encoding now: the log's H.264 keyframe (ms) | {costs['now']:.2f} |\n"
        f"| before: JPEG q90 for the log + H.264 for export (ms) | {costs['jpeg']:.2f} + "
        f"{costs['video']:.2f} = {before:.2f} |\n"
        f"| now / before | {costs['now'] / before:.2f} |"
    )


if __name__ == "__main__":
    typer.run(main)
