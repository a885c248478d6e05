"""``twinrl twin``: the twin built from a phone video."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.table import Table

from twinrl_data.console import progress
from twinrl_data.errors import UsageError

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.settings_cli import name_flags, parse_numbers
from twinrl_sim.cli.common import console
from twinrl_sim.tasks import TASKS

name_flags(
    tag_points="--tag-point",
    object_meshes="--object-mesh",
    camera_images="--camera-image",
    densities="--density",
)

if TYPE_CHECKING:
    pass


twin_app = typer.Typer(
    help="Build the twin of a cell from a phone video of it.", no_args_is_help=True
)


def parse_assignments(values: list[str] | None, option: str) -> dict[str, str]:
    """``NAME=VALUE`` options as a mapping; a malformed one is refused by name."""
    parsed = {}
    for value in values or []:
        name, sep, rest = value.partition("=")
        if not sep or not name.strip() or not rest.strip():
            raise UsageError(f"{option} '{value}' must look like NAME=VALUE")
        parsed[name.strip()] = rest.strip()
    return parsed


def _tag_id(text: str) -> int:
    if not text.isdigit():
        raise UsageError(f"--tag-point '{text}=...' must start with a tag id, e.g. 3=0.4,0.2,0")
    return int(text)


@twin_app.command("build")
def build_command(
    source: Annotated[
        Path, typer.Argument(help="Walk-around video of the cell, or a folder of its photos.")
    ],
    out: Annotated[
        Path, typer.Option(help="Folder for scene.yaml, meshes/, report.md (+ PNGs), .rrd.")
    ],
    tag_size: Annotated[
        float | None,
        typer.Option(help="Edge of the AprilTag 36h11's black square (m), e.g. 0.08."),
    ] = None,
    tag_pose: Annotated[
        str | None,
        typer.Option(
            help="The tag's centre and orientation in the robot-base frame: 'x y z qw qx qy "
            "qz' (m; a tag lying flat, printed x along the base's x: 'x y z 1 0 0 0'). "
            "Needs --tag-size."
        ),
    ] = None,
    tag_id: Annotated[
        int | None,
        typer.Option(help="The tag --tag-pose measures (default: the only one seen)."),
    ] = None,
    tag_point: Annotated[
        list[str] | None,
        typer.Option(
            help="ID=x,y,z: the centre of tag ID in the robot-base frame (m), instead of "
            "--tag-pose; 3 or more tags, not on one line. Repeatable."
        ),
    ] = None,
    task: Annotated[
        str | None,
        typer.Option(
            help=f"Task whose cell was filmed ({', '.join(TASKS)}): objects are named after "
            "its objects, and its robot, cameras and physics are kept."
        ),
    ] = None,
    object_mesh: Annotated[
        list[str] | None,
        typer.Option(
            help="NAME=FILE: a scan or CAD mesh (metres) of object NAME, registered to its "
            "points by ICP instead of the reconstructed shape. Repeatable."
        ),
    ] = None,
    camera_image: Annotated[
        list[str] | None,
        typer.Option(
            help="NAME=IMAGE: a photo from fixed camera NAME (e.g. front=front.png); the "
            "twin's camera is placed at its pose with its focal length. Repeatable."
        ),
    ] = None,
    density: Annotated[
        list[str] | None,
        typer.Option(help="NAME=KG_PER_M3 for an object's mass (default 700). Repeatable."),
    ] = None,
    frames: Annotated[int, typer.Option(help="Frames to keep for SfM.", min=12)] = 150,
    name: Annotated[str | None, typer.Option(help="Scene name (default: from the task).")] = None,
    keep_work: Annotated[
        bool, typer.Option(help="Keep the frames and the COLMAP database under OUT/work.")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seeds SfM, RANSAC and the decomposition.")] = 0,
) -> None:
    """Reconstruct a cell from a walk-around video: frames, SfM (pycolmap), metric scale
    and robot-base frame from AprilTags (one tag's pose, or 3+ tags' centres), table
    plane, objects (meshes, CoACD parts, mass), fixed cameras from photos; write a scene
    spec that every twinrl command takes as --twin, with a report and a Rerun recording."""
    # Imported here: open3d, pycolmap and CoACD take seconds to load.
    from twinrl_sim.reconstruct.pipeline import STAGES, BuildSettings, build_twin

    settings = BuildSettings(
        tag_size=tag_size,
        tag_pose=parse_numbers(tag_pose, "--tag-pose") if tag_pose is not None else None,
        tag_id=tag_id,
        tag_points={
            _tag_id(k): parse_numbers(v, "--tag-point")
            for k, v in parse_assignments(tag_point, "--tag-point").items()
        },
        task=task,
        object_meshes={
            k: Path(v) for k, v in parse_assignments(object_mesh, "--object-mesh").items()
        },
        camera_images={
            k: Path(v) for k, v in parse_assignments(camera_image, "--camera-image").items()
        },
        densities={
            k: parse_numbers(v, "--density")[0]
            for k, v in parse_assignments(density, "--density").items()
        },
        frames=frames,
        name=name,
        keep_work=keep_work,
        seed=seed,
    )
    with progress() as bar:
        job = bar.add_task("twin build", total=len(STAGES))

        def advance(stage: str) -> None:
            bar.update(job, description=stage, completed=STAGES.index(stage))

        built = build_twin(source, out, settings, on_stage=advance)
    table = Table(title=f"{built.scene.name}: {len(built.objects)} objects")
    for column in ("object", "role", "x (m)", "y (m)", "yaw (deg)", "mass (kg)", "parts"):
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
        )
    console.print(table)
    console.print(
        f"{built.model.registered}/{built.model.frames} frames registered, tag residual "
        f"{1000 * built.alignment.residual_m:.2f} mm, table top at {built.table.height:+.4f} m, "
        f"{sum(built.seconds.values()):.0f} s"
    )
    console.print(f"{out}/scene.yaml (use as --twin), report.md, reconstruction.rrd")
