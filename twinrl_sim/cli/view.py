"""``twinrl view``: episodes in Rerun, with the twin's link frames."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.errors import UsageError
from twinrl_data.schema import STATE, Episode
from twinrl_sim.cli.common import console
from twinrl_sim.tasks import TASKS, make_task

if TYPE_CHECKING:
    from twinrl_data.view import LinkFrames


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
