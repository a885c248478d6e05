"""``twinrl twin``: the twin built from a phone video."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.table import Table

from twinrl_data.console import progress

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.settings_cli import options, settings_command
from twinrl_sim.cli.common import console
from twinrl_sim.reconstruct.settings import STAGES, Board, BuildSettings

twin_app = typer.Typer(
    help="Build the twin of a cell from a phone video of it.", no_args_is_help=True
)


SOURCE = inspect.Parameter(
    "source",
    inspect.Parameter.KEYWORD_ONLY,
    annotation=Annotated[
        Path,
        typer.Argument(
            help="Walk-around video of the cell, or a folder of its photos.",
            metavar="SOURCE",
            show_default=False,
        ),
    ],
)
OUT = inspect.Parameter(
    "out",
    inspect.Parameter.KEYWORD_ONLY,
    annotation=Annotated[
        Path, typer.Option(help="Folder for scene.yaml, meshes/, report.md (+ PNGs), .rrd.")
    ],
)


def build(settings: dict[str, Any], source: Path, out: Path) -> None:
    """Reconstruct a cell from a walk-around video: frames, SfM (pycolmap), metric scale
    and robot-base frame from AprilTags (one tag's pose, or 3+ tags' centres), table
    plane, objects (meshes, CoACD parts, mass), fixed cameras from photos; write a scene
    spec that every twinrl command takes as --twin, with a report and a Rerun recording."""
    # Imported here: open3d, pycolmap and CoACD take seconds to load.
    from twinrl_sim.reconstruct.pipeline import build_twin
    from twinrl_sim.reconstruct.report import dropped_summary

    config = BuildSettings(**settings)
    with progress() as bar:
        job = bar.add_task("twin build", total=len(STAGES))

        def advance(stage: str) -> None:
            bar.update(job, description=stage, completed=STAGES.index(stage))

        built = build_twin(source, out, config, on_stage=advance)
    table = Table(title=f"{built.scene.name}: {len(built.objects)} objects")
    columns = ("object", "role", "x (m)", "y (m)", "yaw (deg)", "mass (kg)", "parts", "confidence")
    for column in columns:
        table.add_column(column)
    for obj in built.objects:
        table.add_row(
            obj.name,
            obj.role,
            f"{obj.position[0]:.3f}",
            f"{obj.position[1]:.3f}",
            f"{np.degrees(obj.yaw):+.1f}",
            f"{obj.mass:.3f}" if obj.role == "manipulated" else "fixed",
            str(len(obj.shape.parts)),
            obj.evidence.confidence,
        )
    console.print(table)
    console.print(
        f"{built.model.registered}/{built.model.frames} frames registered, tag residual "
        f"{1000 * built.alignment.residual_m:.2f} mm, table top at {built.table.height:+.4f} m, "
        f"{sum(built.seconds.values()):.0f} s"
    )
    if built.look_score is not None:
        look = built.look_score
        console.print(
            f"look, from {look.frames} held-out frames: PSNR {look.psnr:.1f} dB, SSIM "
            f"{look.ssim:.3f} (flat colours: {look.flat_psnr:.1f} dB, {look.flat_ssim:.3f})"
        )
    if dropped := dropped_summary(built.dropped):
        console.print(dropped)
    console.print(f"{out}/scene.yaml (use as --twin), report.md, reconstruction.rrd")


settings_command(
    twin_app,
    "build",
    options(
        BuildSettings,
        names={
            "tag_points": "tag_point",
            "object_meshes": "object_mesh",
            "camera_images": "camera_image",
            "densities": "density",
        },
    ),
    build,
    help=build.__doc__ or "",
    extra=[SOURCE, OUT],
)


CLIP = SOURCE.replace(
    annotation=Annotated[
        Path,
        typer.Argument(
            help="Clip (or folder of frames) of the printed board, filmed with the camera "
            "and zoom that film the cell.",
            metavar="SOURCE",
            show_default=False,
        ),
    ]
)
CALIBRATION_OUT = OUT.replace(
    annotation=Annotated[
        Path, typer.Option(help="Calibration file to write (OpenCV YAML), e.g. phone.yaml.")
    ]
)


def calibrate(settings: dict[str, Any], source: Path, out: Path) -> None:
    """Estimate the filming camera's intrinsics (pinhole, k1 k2 p1 p2) from a clip of a
    printed checkerboard or ChArUco board, for twin build --calibration."""
    from twinrl_sim.reconstruct.calibration import calibrate as solve
    from twinrl_sim.reconstruct.calibration import check_new_file, write_calibration

    board = Board(**settings)
    check_new_file(out)  # before the clip is read
    with progress() as bar:
        job = bar.add_task("frames searched", total=None)
        solved = solve(source, board, on_frame=lambda n: bar.update(job, completed=n))
    write_calibration(solved, out)
    fx, fy, cx, cy, k1, k2, p1, p2 = solved.intrinsics
    console.print(
        f"fx {fx:.1f} fy {fy:.1f} cx {cx:.1f} cy {cy:.1f} px, k1 {k1:+.4f} k2 {k2:+.4f} "
        f"p1 {p1:+.5f} p2 {p2:+.5f} at {solved.size[0]}x{solved.size[1]}; reprojection "
        f"{solved.rms_px:.2f} px RMS over {solved.views} views ({solved.frames} frames read)"
    )
    console.print(f"{out} (use as twinrl twin build --calibration {out})")


settings_command(
    twin_app,
    "calibrate",
    options(Board),
    calibrate,
    help=calibrate.__doc__ or "",
    extra=[CLIP, CALIBRATION_OUT],
)
