"""Twin build speed and accuracy: a rendered 60-second walk-around clip of the
pick-and-place cell (30 fps) and a photo from its front camera, built into a scene spec
with ``build_twin`` (150 frames, as ``twinrl twin build`` does by default).

Target: at most 10 minutes end to end on 2 cores (rendering the clip is not counted).
Frame selection streams the clip: its peak memory (tracemalloc) is reported as a ratio
to the decoded clip's size.
Accuracy is measured against the scene that rendered the clip. The base frame comes from
one tag's pose, or with ``--tag-points`` from the centres of three tags. Usage::

    python bench/bench_reconstruct.py --seconds 60
    python bench/bench_reconstruct.py --seconds 60 --tag-points
"""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from twinrl_robot.scripted import run_scripted_expert
from twinrl_sim.build import compile_scene
from twinrl_sim.reconstruct.frames import select_frames
from twinrl_sim.reconstruct.objects import template_sizes
from twinrl_sim.reconstruct.pipeline import BuildSettings, build_twin
from twinrl_sim.reconstruct.synthetic import (
    ONE_TAG,
    THREE_TAGS,
    WalkthroughSettings,
    render_fixed_view,
    render_walkthrough,
)
from twinrl_sim.tasks import make_task

TARGET_SECONDS = 600.0


def main(
    seconds: Annotated[float, typer.Option(help="Length of the rendered clip.")] = 60.0,
    fps: Annotated[float, typer.Option(help="Frame rate of the rendered clip.")] = 30.0,
    frames: Annotated[int, typer.Option(help="Frames kept for SfM.")] = 150,
    seed: Annotated[int, typer.Option(help="Seed of the clip and the build.")] = 0,
    tag_points: Annotated[
        bool, typer.Option(help="Three tags, aligned by their centres, not one tag's pose.")
    ] = False,
) -> None:
    scene = make_task("pick_place").scene
    tags = THREE_TAGS if tag_points else ONE_TAG
    clip = WalkthroughSettings(seconds=seconds, fps=fps)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        start = time.perf_counter()
        walk = render_walkthrough(
            scene,
            root / "walk.mp4",
            tags=tags,
            settings=clip,
            seed=seed,
        )
        front = render_fixed_view(scene, "front", root / "front.png", tags=tags)
        rendered = time.perf_counter() - start
        tracemalloc.start()
        probe = select_frames(walk.video, root / "probe", target=frames)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        clip_bytes = probe.frames_in_clip * clip.width * clip.height * 3
        reference = (
            {"tag_points": {i: tuple(pose[:3]) for i, pose in walk.tag_poses.items()}}
            if tag_points
            else {"tag_size": tags[0].size, "tag_pose": tuple(walk.tag_poses[0])}
        )
        settings = BuildSettings(
            **reference,
            task="pick_place",
            camera_images={"front": front},
            frames=frames,
            seed=seed,
        )
        start = time.perf_counter()
        built = build_twin(walk.video, root / "cell", settings)
        elapsed = time.perf_counter() - start
        compile_scene(built.scene)
        expert = run_scripted_expert("pick_place", episodes=5, scene=built.scene)
    print(f"clip: {seconds:g} s at {fps:g} fps, rendered in {rendered:.0f} s (not counted)")
    print(
        f"frame selection peak memory {peak / 1e6:.0f} MB = {peak / clip_bytes:.3f}x the "
        f"decoded clip ({clip_bytes / 1e6:.0f} MB)"
    )
    print(
        f"build: {elapsed:.0f} s = {elapsed / TARGET_SECONDS:.2f}x the {TARGET_SECONDS:.0f} s "
        "target; " + ", ".join(f"{k} {v:.0f} s" for k, v in built.seconds.items())
    )
    print(
        f"frames registered {built.model.registered}/{built.model.frames}, "
        f"{len(built.model.points)} points, {built.alignment.reference} residual "
        f"{1000 * built.alignment.residual_m:.2f} mm"
    )
    truth_path = walk.camera_positions[built.selection.source_indices]
    camera_error = np.median(np.linalg.norm(built.camera_path - truth_path, axis=1))
    print(
        f"table height error {1000 * abs(built.table.height - scene.table.top_height):.1f} mm; "
        f"camera path error {1000 * camera_error:.1f} mm (median)"
    )
    truth = template_sizes(scene)
    for obj in built.objects:
        centre, extent = truth[obj.name]
        size = np.array([*sorted(obj.cluster.size[:2], reverse=True), obj.cluster.size[2]])
        size_error = 100 * (size / extent - 1)
        yaw_error = np.degrees(abs(np.angle(np.exp(2j * (obj.yaw - scene.object(obj.name).yaw)))))
        print(
            f"{obj.name}: position error {1000 * np.linalg.norm(obj.position - centre):.1f} mm, "
            f"yaw error {yaw_error / 2:.1f} deg (mod 180), size error "
            + "/".join(f"{e:+.0f}" for e in size_error)
            + " % (long/short/height)"
        )
    front_truth = scene.cameras[0]
    placed = built.scene.cameras[0]
    print(
        f"front camera: position error "
        f"{1000 * np.linalg.norm(np.subtract(placed.pos, front_truth.pos)):.1f} mm, "
        f"fovy {placed.fovy:.1f} deg (true {front_truth.fovy:.1f})"
    )
    success = np.mean([e.success for e in expert.episodes])
    print(f"scripted expert in the built scene: {100 * success:.0f} % of {len(expert.episodes)}")


if __name__ == "__main__":
    typer.run(main)
