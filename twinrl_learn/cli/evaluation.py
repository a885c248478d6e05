"""``twinrl eval`` and ``twinrl locate``: how a policy does, and where it sees things."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from twinrl_data.console import progress
from twinrl_data.errors import UsageError
from twinrl_data.settings_cli import parse_grid
from twinrl_learn.cli.common import DeviceOption, console
from twinrl_robot.backends import WORLDS
from twinrl_robot.cli import CellOption, EmulatedOption, check_real
from twinrl_sim.tasks import TASKS, make_task


def eval_command(
    checkpoint: Annotated[
        str, typer.Argument(help="twinrl checkpoint, lerobot pretrained_model folder, or 'expert'.")
    ],
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")],
    out: Annotated[Path, typer.Option(help="Folder for episodes, eval.json and heatmap.png.")],
    world: Annotated[str, typer.Option(help="twin, plant or real (with --cell).")] = "twin",
    effects: Annotated[Path | None, typer.Option(help="Hidden effects YAML for the plant.")] = None,
    cell: CellOption = None,
    emulated: EmulatedOption = False,
    grid: Annotated[
        str, typer.Option(help="Grid of target positions over ID and OOD, e.g. 8x8.")
    ] = "8x8",
    episodes: Annotated[int, typer.Option(help="Episodes per grid cell.", min=1)] = 1,
    seed: Annotated[int, typer.Option(help="Seed for object placement and sampling.")] = 0,
    open_loop: Annotated[
        bool,
        typer.Option(
            help="Run a twinrl policy's action chunks open-loop instead of averaging every "
            "prediction for each step (temporal ensembling)."
        ),
    ] = False,
    grasp_hold: Annotated[
        bool | None,
        typer.Option(
            help="Hold a twinrl policy's arm while the gripper closes, or not (default: as "
            "the checkpoint says; checkpoints hold)."
        ),
    ] = None,
    binary_gripper: Annotated[
        bool | None,
        typer.Option(
            help="Command a twinrl policy's gripper open or closed, or as predicted (default: "
            "as the checkpoint says; checkpoints command it open or closed)."
        ),
    ] = None,
    close_as_demonstrated: Annotated[
        bool | None,
        typer.Option(
            help="Hold a twinrl policy's close until the tool is as low over the object as "
            "the demonstrations close, or close when it says (default: as the checkpoint "
            "says; checkpoints hold)."
        ),
    ] = None,
    device: DeviceOption = "auto",
) -> None:
    """Roll a policy out over a grid covering ID and OOD; success per region and a heatmap."""
    from twinrl_learn.evaluate import evaluate
    from twinrl_learn.runners import load_runner

    if task not in TASKS:
        make_task(task)  # raises with the nearest task name
    if world not in WORLDS:
        raise UsageError(f"--world must be one of {', '.join(WORLDS)}, got '{world}'")
    check_real([world], cell, emulated)
    if world != "plant" and effects is not None:
        raise UsageError("--effects applies to --world plant only")
    if effects is not None and not effects.is_file():
        raise UsageError(f"--effects {effects} does not exist")
    runner = load_runner(
        checkpoint,
        open_loop=open_loop,
        grasp_hold=grasp_hold,
        binary_gripper=binary_gripper,
        close_as_demonstrated=close_as_demonstrated,
        device=device,
    )
    with progress("success") as bar:
        job = bar.add_task(f"{runner.name} in the {world}", total=None, success="0")
        done = {"n": 0, "ok": 0}

        def advance(cell, success: bool) -> None:
            done["n"] += 1
            done["ok"] += success
            bar.update(job, advance=1, success=f"{done['ok']}/{done['n']}")

        report = evaluate(
            runner,
            task,
            world=world,
            effects=effects,
            grid=parse_grid(grid, "--grid"),
            episodes=episodes,
            seed=seed,
            out=out,
            on_episode=advance,
            cell_file=cell,
            emulated=emulated,
        )
    table = Table("region", "success", "episodes", title=f"{task}: {runner.name} in the {world}")
    for region, rate in report.success_rate().items():
        count = sum(c.episodes for c in report.cells if c.region == region)
        table.add_row(region, f"{100 * rate:.0f} %", str(count))
    console.print(table)
    console.print(f"{out / 'eval.json'}, {out / 'heatmap.png'}, episodes in {out / 'session'}")


def labelled_sources(texts: list[str]) -> dict[str, Path]:
    """``LABEL=PATH`` or ``PATH`` (labelled by its folder name, or a session's by its
    parent's) -> {label: path}. A path that exists is a path, even with an ``=`` in it."""
    sources: dict[str, Path] = {}
    for text in texts:
        named = "=" in text and not Path(text).exists()
        label, path = text.split("=", 1) if named else ("", text)
        path = Path(path)
        label = label or (path.parent.name if path.name == "session" else path.name)
        if not path.exists():
            raise UsageError(
                f"{path} does not exist (give a session, .mcap, catalog or LeRobot dataset)"
            )
        if label in sources:
            raise UsageError(f"two sources are labelled '{label}'; name them LABEL=PATH")
        sources[label] = path
    return sources


def locate_command(
    checkpoint: Annotated[
        Path,
        typer.Argument(
            help="twinrl image-policy checkpoint (locating head or pose estimator), or a pose "
            "estimator folder (`twinrl train perception`)."
        ),
    ],
    sources: Annotated[
        list[str],
        typer.Argument(
            help="Episodes to replay: session folders (e.g. an eval's OUT/session), .mcap "
            "files, catalog .parquet files or LeRobot datasets, each PATH or LABEL=PATH."
        ),
    ],
    out: Annotated[Path, typer.Option(help="Folder for locating.json and locating.png.")],
) -> None:
    """How far off an image policy's locating head or a pose estimator sees the objects in
    logged episodes.

    By the TCP's distance to each object, per source and region: its training demos
    against its own rollouts, say."""
    from twinrl_learn.locating import band_labels, locating_errors

    labelled = labelled_sources(sources)
    with progress() as bar:
        job = bar.add_task("replaying episodes", total=None)
        report = locating_errors(
            checkpoint,
            labelled,
            out,
            on_episode=lambda _: bar.update(job, advance=1),
            on_start=lambda total: bar.update(job, total=total),
        )
    bands = band_labels(report["bands_cm"])
    table = Table(
        "source",
        "region",
        "object",
        "first frame",
        *[f"{b} cm" for b in bands],
        title=f"median planar locating error (cm) by TCP-to-object distance: {checkpoint.name}",
    )
    for label, regions in report["sources"].items():
        for region, objects in regions.items():
            for name, errors in objects.items():
                cells = ["–" if m is None else f"{m:.1f}" for m in errors["median_cm"]]
                table.add_row(label, region, name, f"{errors['first_frame_cm']:.1f}", *cells)
    console.print(table)
    console.print(f"{out / 'locating.json'}, {out / 'locating.png'}")


def judge_command(
    classifier: Annotated[
        Path, typer.Argument(help="Reward classifier folder (`twinrl train reward-classifier`).")
    ],
    paths: Annotated[
        list[Path],
        typer.Argument(
            help="Episodes it never saw: session folders, .mcap files or LeRobot datasets; "
            "only its task's are judged."
        ),
    ],
    out: Annotated[
        Path | None, typer.Option(help="JSON file to write the scores to (must not exist).")
    ] = None,
    success_frames: Annotated[
        int,
        typer.Option(
            help="Successive frames judged a success that end an episode as one, as real "
            "RL's --success-frames.",
            min=1,
        ),
    ] = 1,
) -> None:
    """How a reward classifier judges logged episodes: frame scores, and per episode the
    false successes (a failed episode real RL would have rewarded) and missed successes."""
    if out is not None and out.exists():
        raise UsageError(f"--out {out} exists; choose another file")
    from twinrl_learn.reward_check import check_reward_classifier, save_check
    from twinrl_learn.reward_classifier import RewardClassifier, episodes_under

    judge = RewardClassifier.load(classifier)
    episodes = episodes_under(paths, judge.settings.cameras, judge.task)
    check = check_reward_classifier(judge, episodes, success_frames)
    table = Table("frames (successes)", "accuracy", "balanced", "precision", "recall",
                  title=f"{classifier.name}: {check.task}")  # fmt: skip
    table.add_row(
        f"{check.frames} ({check.positives})",
        *[f"{100 * v:.1f} %" for v in (check.accuracy, check.balanced_accuracy,
                                       check.precision, check.recall)],
    )  # fmt: skip
    console.print(table)
    near = f", {check.near_miss_false_successes} of {check.near_miss_episodes} near misses"
    needing = f" ({success_frames} successive frames make one)" if success_frames > 1 else ""
    console.print(
        f"false successes{needing}: {check.false_successes} of {check.failed_episodes} "
        "failed episodes"
        f"{near if check.near_miss_episodes else ''}; missed successes: "
        f"{check.missed_successes} of {check.successful_episodes}; per episode precision "
        f"{100 * check.episode_precision:.1f} %, recall {100 * check.episode_recall:.1f} %"
    )
    if out is not None:
        console.print(f"{save_check(check, out)}")
