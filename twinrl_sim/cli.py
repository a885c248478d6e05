"""``twinrl sim``: look at the simulated cell."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.console import progress, quiet_encoders
from twinrl_data.errors import UsageError
from twinrl_data.schema import STATE, Episode
from twinrl_sim.gap.candidates import CANDIDATES, IMAGE_EFFECTS
from twinrl_sim.randomize import KINDS as RANDOMIZATIONS
from twinrl_sim.tasks import TASKS, TaskConfig, make_task, task_on_twin, twin_scene

if TYPE_CHECKING:
    from twinrl_data.view import LinkFrames

app = typer.Typer(
    help="The MuJoCo twin: render cells, run experts, list effects.", no_args_is_help=True
)
console = Console(soft_wrap=True)  # paths and figures are never broken across lines


def parse_config(text: str) -> TaskConfig:
    """A configuration from inline JSON or from a JSON file path."""
    path = Path(text)
    source = path.read_text() if path.suffix == ".json" and path.is_file() else text
    try:
        data = json.loads(source)
    except json.JSONDecodeError as err:
        raise UsageError(
            "--config must be JSON like "
            '\'{"object": [0.45, -0.2, 0.3], "target": [0.5, -0.1, 0]}\' '
            f"or a .json file ({err.msg})"
        ) from None
    return TaskConfig.from_dict(data)


def refuse_overwrite(path: Path, force: bool) -> None:
    if path.exists() and not force:
        raise UsageError(
            f"{path} already exists; pass --force to overwrite it or choose another --out"
        )


@app.command()
def show(
    task: Annotated[str, typer.Argument(help=f"Task: {', '.join(TASKS)}.")],
    config: Annotated[
        str | None, typer.Option(help="Configuration as JSON or a .json file.")
    ] = None,
    region: Annotated[str | None, typer.Option(help="Sample a configuration in ID or OOD.")] = None,
    seed: Annotated[int, typer.Option(help="Seed for the sampled configuration.")] = 0,
    size: Annotated[int, typer.Option(help="Image width and height (pixels).")] = 480,
    out: Annotated[Path | None, typer.Option(help="PNG to write (default: TASK.png).")] = None,
    force: Annotated[bool, typer.Option(help="Overwrite --out if it exists.")] = False,
) -> None:
    """Render the cell of TASK from every camera, side by side, to a PNG."""
    import PIL.Image

    from twinrl_sim.env import TwinEnv

    out = out or Path(f"{task}.png")
    if out.suffix.lower() != ".png":
        raise UsageError(f"--out must end in .png, got {out}")
    refuse_overwrite(out, force)
    env = TwinEnv(task, region=region)
    try:
        options = {"config": parse_config(config)} if config else None
        env.reset(seed=seed, options=options)
        frames = [env.cell.render(cam, width=size, height=size) for cam in env.cell.layout.cameras]
    finally:
        env.close()
    PIL.Image.fromarray(np.hstack(frames)).save(out)
    assert env.config is not None
    console.print(
        f"{out}: {task} ({env.task.region_of(env.config) or 'no region'}) "
        f"config {json.dumps(env.config.to_dict())}, cameras {', '.join(env.cell.layout.cameras)}"
    )


@app.command()
def effects() -> None:
    """List the physical effects the twin and the plant understand."""
    from twinrl_sim.effects import describe_effects

    table = Table("effect", "parameters", "models")
    for name, params, doc in describe_effects():
        table.add_row(name, params, doc)
    console.print(table)


def load_target(target: str, default_episode: int) -> Episode:
    """An episode from ``PATH`` or ``PATH#N``: an .mcap file, a session or a dataset."""
    from twinrl_data.sources import open_episode

    return open_episode(target, default_episode)


def twin_link_frames(episode: Episode) -> LinkFrames | None:
    """FK of the built-in twin for episodes of a built-in task with joint names logged."""
    from twinrl_sim.build import compile_scene
    from twinrl_sim.kinematics import LinkFrames as TwinLinkFrames

    if episode.meta.task not in TASKS or episode.meta.robot != "ur5e":
        return None
    names = episode.meta.names.get(STATE, [])
    try:
        return TwinLinkFrames(compile_scene(make_task(episode.meta.task).scene), names)
    except ValueError:
        return None


def view(
    targets: Annotated[
        list[str],
        typer.Argument(help="Episodes: .mcap, session or dataset folder, each optionally PATH#N."),
    ],
    episode: Annotated[int, typer.Option(help="Episode index in a session or dataset.")] = 0,
    save: Annotated[
        Path | None, typer.Option(help="Write an .rrd instead of opening the viewer.")
    ] = None,
    force: Annotated[bool, typer.Option(help="Overwrite --save if it exists.")] = False,
) -> None:
    """Inspect episodes in Rerun; two or more are overlaid on one timeline."""
    from twinrl_data.view import save_rrd, spawn_viewer

    episodes = [load_target(t, episode) for t in targets]
    link_frames = twin_link_frames(episodes[0])
    if save is not None:
        if save.suffix != ".rrd":
            raise UsageError(f"--save must end in .rrd, got {save}")
        save_rrd(episodes, save, link_frames=link_frames, force=force)
        console.print(f"{save}: {len(episodes)} episode(s), open it with `rerun {save}`")
    else:
        spawn_viewer(episodes, link_frames=link_frames)


def expand_command(
    task: Annotated[str, typer.Argument(help=f"Task: {', '.join(TASKS)}.")],
    out: Annotated[Path, typer.Option(help="Folder for the session, the dataset and expand.json.")],
    id_count: Annotated[
        int, typer.Option("--id", help="Demonstrations in the ID region.", min=0)
    ] = 30,
    ood_count: Annotated[
        int, typer.Option("--ood", help="Demonstrations in the OOD region.", min=0)
    ] = 30,
    method: Annotated[
        str, typer.Option(help="plan (grasp sampling + planner) or augment.")
    ] = "plan",
    from_demo: Annotated[
        Path | None, typer.Option(help="Recorded demonstration (.mcap) to re-target with augment.")
    ] = None,
    randomize: Annotated[
        str,
        typer.Option(
            help=f"Visual randomisation: comma-separated {', '.join(RANDOMIZATIONS)}, or all."
        ),
    ] = "",
    twin: Annotated[
        str | None,
        typer.Option(
            help="Scene spec to synthesize in (e.g. twin_fitted.yaml from `gap diagnose`, "
            "with the cell's physics and look); default: the task's built-in cell."
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option(help="Seed (attempt k always gets the same configuration).")
    ] = 0,
    workers: Annotated[int, typer.Option(help="Worker processes (default: 2).", min=1)] = 2,
    images: Annotated[
        bool,
        typer.Option(
            help="Render and record the front and wrist cameras; --no-images for demos a "
            "state policy learns from (several times faster)."
        ),
    ] = True,
    detours: Annotated[
        float,
        typer.Option(
            help="Share of the demos (plan only) whose arm first strays to a point 8-20 cm "
            "beside the object and does the task from there: views off the straight path, "
            "and the way back, for an image policy.",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    force: Annotated[bool, typer.Option(help="Replace --out if it exists.")] = False,
) -> None:
    """Synthesize twin demonstrations across ID and OOD (TwinRL's exploration-space expansion)."""
    from twinrl_sim.expand import expand

    kinds = RANDOMIZATIONS if randomize == "all" else tuple(k for k in randomize.split(",") if k)
    scene = task_on_twin(task, twin) if twin is not None else None
    quiet_encoders()
    with progress("kept") as bar:
        jobs = {
            "ID": bar.add_task(f"{task} ID attempts", total=None, kept=0),
            "OOD": bar.add_task(f"{task} OOD attempts", total=None, kept=0),
        }
        kept = {"ID": 0, "OOD": 0}

        def advance(region: str, success: bool) -> None:
            kept[region] += success
            bar.update(jobs[region], advance=1, kept=kept[region])

        report = expand(
            task,
            id_count=id_count,
            ood_count=ood_count,
            out=out,
            method=method,
            from_demo=from_demo,
            randomize=kinds,
            scene=scene,
            seed=seed,
            workers=workers,
            images=images,
            detours=detours,
            force=force,
            on_demo=advance,
        )
    table = Table(
        "region", "requested", "kept", "attempts", "yield", title=f"{task}: {method} demonstrations"
    )
    for region, requested in report.requested.items():
        table.add_row(
            region,
            str(requested),
            str(report.kept.get(region, 0)),
            str(report.attempts.get(region, 0)),
            f"{100 * report.yield_rate[region]:.0f} %",
        )
    console.print(table)
    if detours:
        console.print(f"{sum(report.detoured.values())} of the kept demos stray first")
    console.print(
        f"synthesis {report.seconds_synthesis:.1f} s, export {report.seconds_export:.1f} s; "
        f"episodes in {report.session}, dataset {report.dataset or '(none)'}"
    )


def import_csv_command(
    files: Annotated[list[Path], typer.Argument(help="CSV logs, one episode each.")],
    out: Annotated[Path, typer.Option(help="Session folder to create with the episodes.")],
    format: Annotated[
        str, typer.Option("--format", help="rtde (UR's RTDE recorder columns) or generic.")
    ] = "rtde",
    column_map: Annotated[
        Path | None,
        typer.Option("--map", help="YAML column map (required with --format generic)."),
    ] = None,
    fps: Annotated[
        float | None, typer.Option(help="Resample to this rate (default: the log's own).")
    ] = None,
    twin: Annotated[
        str,
        typer.Option(help="Built-in cell or scene spec whose robot computes missing TCP poses."),
    ] = "pick_place",
    world: Annotated[str, typer.Option(help="real or plant: where the log was measured.")] = "real",
    task: Annotated[str, typer.Option(help="Task label of the episodes.")] = "arm",
) -> None:
    """Import joint logs recorded outside twinrl as episodes (source ``imported``).

    A generic column map is YAML: ``time``, ``time_unit`` (s|ms|us|ns), ``angle_unit``
    (rad|deg), ``layout`` (wide|long), ``commanded``/``measured`` (one column per joint),
    optional ``velocity``, ``effort`` (N m), ``tcp`` (x y z rx ry rz), ``joints``.
    """
    from twinrl_data.importers import RTDE_MAP, ColumnMap, import_csv
    from twinrl_data.session import Session
    from twinrl_sim.build import compile_scene
    from twinrl_sim.kinematics import TcpKinematics

    if format not in ("rtde", "generic"):
        raise UsageError(f"--format must be rtde or generic, got '{format}'")
    if format == "generic" and column_map is None:
        raise UsageError("--format generic needs --map COLUMNS.yaml (see --help for its keys)")
    cmap = ColumnMap.load(column_map) if column_map else RTDE_MAP
    kinematics = TcpKinematics(compile_scene(twin_scene(twin)))
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"{out} exists and is not empty; choose another --out")
    episodes = [
        import_csv(f, cmap, fps=fps, task=task, world=world, forward_kinematics=kinematics)
        for f in files
    ]  # every file is read before anything is written
    session = Session.create(out)
    for episode in episodes:
        session.add(episode)
        console.print(
            f"{episode.meta.policy}: {len(episode)} steps at {episode.meta.fps:g} Hz, "
            f"fields {', '.join(sorted(episode.data))}"
        )
    console.print(f"{out}: {len(episodes)} episodes imported")


gap_app = typer.Typer(
    help="The sim-to-real gap: where measured episodes and the twin disagree.",
    no_args_is_help=True,
)


@gap_app.command("localize")
def localize_command(
    measured: Annotated[
        list[Path], typer.Argument(help="Measured episodes: sessions, .mcap files, datasets.")
    ],
    out: Annotated[Path, typer.Option(help="Folder for localization.json and .png.")],
    twin: Annotated[
        str, typer.Option(help=f"Built-in cell ({', '.join(TASKS)}) or a scene spec file.")
    ] = "pick_place",
    window: Annotated[int, typer.Option(help="Steps per shooting window.", min=2)] = 20,
) -> None:
    """Replay measured episodes in the twin (restarting from the measurement every
    --window steps) and show where they disagree: RMS, bias, gain and lag per signal,
    split by motion regime."""
    from twinrl_data.sources import discover_episodes
    from twinrl_sim.gap.localize import localize, plot_localization
    from twinrl_sim.gap.shooting import replay_windows

    scene = twin_scene(twin)
    episodes = discover_episodes(measured)
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"{out} exists and is not empty; choose another --out")
    replays = []
    with progress() as bar:
        job = bar.add_task("replay in the twin", total=len(episodes))
        for episode in episodes:
            replays.append(replay_windows(episode, scene, window=window))
            bar.advance(job)
    rows = localize(replays)
    out.mkdir(parents=True, exist_ok=True)
    (out / "localization.json").write_text(
        json.dumps(
            {"episodes": len(episodes), "window": window, "rows": [r.to_dict() for r in rows]},
            indent=1,
        )
    )
    plot_localization(rows, out / "localization.png")
    console.print(localization_table(rows, f"{len(episodes)} episodes against the twin '{twin}'"))
    console.print(f"{out}/localization.json, localization.png")


def localization_table(rows: list, title: str) -> Table:
    table = Table(title=title)
    for column in ("signal", "RMS", "bias", "gain", "lag (ms)", "worst regime"):
        table.add_column(column)
    for r in rows:
        worst = max(r.regimes, key=r.regimes.get) if r.regimes else "-"
        table.add_row(
            r.signal,
            f"{r.rms:.2e} {r.unit}",
            f"{r.bias:+.2e}",
            f"{r.gain:.3f}",
            f"{1000 * r.lag_s:+.0f}",
            worst,
        )
    return table


@gap_app.command("diagnose")
def diagnose_command(
    measured: Annotated[
        list[Path], typer.Argument(help="Measured episodes: sessions, .mcap files, datasets.")
    ],
    out: Annotated[
        Path,
        typer.Option(
            help="Folder for gap_report.json, twin_fitted.yaml, report.md (+ PNGs), overlay.rrd."
        ),
    ],
    twin: Annotated[
        str, typer.Option(help=f"Built-in cell ({', '.join(TASKS)}) or a scene spec file.")
    ] = "pick_place",
    heldout: Annotated[
        float, typer.Option(help="Fraction of the episodes held out to judge the fits.")
    ] = 0.3,
    effects_allowed: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated candidates to try (default: all of "
            f"{', '.join(CANDIDATES)}, and {' and '.join(IMAGE_EFFECTS)} when images are logged)."
        ),
    ] = None,
    window: Annotated[int, typer.Option(help="Control steps per shooting window.", min=2)] = 20,
    noise: Annotated[
        str,
        typer.Option(
            help="Sensor noise per signal family, the residuals' unit, e.g. 'q=2e-4,tau=0.1' "
            "(families: q rad, qd rad/s, tcp m, tau N m, object m, image: standardised grey, "
            "colour: 0-1)."
        ),
    ] = "",
    seed: Annotated[int, typer.Option(help="Seeds the held-out split and window choice.")] = 0,
) -> None:
    """Name the physical effects the twin lacks: fit every candidate effect to the
    measured episodes (mujoco.sysid over shooting windows), keep the one that held-out
    episodes and BIC support, repeat until none is significant, and write the fitted
    twin with a report of the gap before and after."""
    from twinrl_data.sources import discover_episodes
    from twinrl_sim.gap.diagnose import diagnose
    from twinrl_sim.gap.identify import NoiseFloor
    from twinrl_sim.gap.localize import localize
    from twinrl_sim.gap.report import format_params, write_report
    from twinrl_sim.gap.shooting import replay_windows

    scene = twin_scene(twin)
    noise_floor = NoiseFloor.parse(noise)
    allowed = (
        [e.strip() for e in effects_allowed.split(",") if e.strip()] if effects_allowed else None
    )
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"{out} exists and is not empty; choose another --out")
    images = allowed is None or any(e in allowed for e in IMAGE_EFFECTS)
    episodes = discover_episodes(measured, images=images)
    with progress() as bar:
        job = bar.add_task("diagnose", total=None)
        diagnosis = diagnose(
            episodes,
            scene,
            heldout=heldout,
            allowed=allowed,
            window=window,
            noise=noise_floor,
            seed=seed,
            log=lambda message: bar.update(job, description=message),
        )
        bar.update(job, description="localise and write the report")
        replays = [replay_windows(e, scene, window=window) for e in episodes]
        rows = localize(replays)
        write_report(diagnosis, rows, scene, out)
    table = Table(title=f"candidates against the twin '{twin}' (round 1, best first)")
    for column in ("effect", "parameters", "held-out error", "ΔBIC", "significant"):
        table.add_column(column)
    for r in diagnosis.candidates:
        table.add_row(
            r.effect,
            format_params(r.params),
            f"{r.heldout_error:.3g}",
            f"{r.delta_bic:+.0f}",
            "yes" if r.significant else "no",
        )
    console.print(table)
    named = ", ".join(s["effect"] for s in diagnosis.selected) or "nothing"
    console.print(
        f"named: {named}; held-out error {diagnosis.gap_before:.3g} -> {diagnosis.gap_after:.3g} "
        f"({100 * diagnosis.heldout_reduction:.1f} % smaller, noise floor 1)"
    )
    if diagnosis.inverse_dynamics:
        before, after = (
            float(np.sqrt(np.mean([g[k] ** 2 for g in diagnosis.inverse_dynamics.values()])))
            for k in ("before", "after")
        )
        console.print(
            f"inverse dynamics: held-out torque error {before:.3g} -> {after:.3g} N m (RMS)"
        )
    for camera, gap in diagnosis.image_gap.items():
        console.print(
            f"{camera} camera: held-out image error {gap['before']:.3g} -> {gap['after']:.3g}"
        )
    if diagnosis.appearance_gap:
        gap = diagnosis.appearance_gap
        console.print(
            f"appearance: held-out colour error {gap['before']:.3g} -> {gap['after']:.3g}"
        )
    console.print(f"{out}/gap_report.json, twin_fitted.yaml, report.md, overlay.rrd")


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


def parse_numbers(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise UsageError(f"{option} '{text}' must be numbers separated by spaces") from None


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
