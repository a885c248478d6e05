"""``twinrl view``: episodes in Rerun, with the twin's cell in 3D."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.errors import UsageError
from twinrl_data.schema import ENVIRONMENT_STATE, STATE, Episode
from twinrl_sim.cli.common import console
from twinrl_sim.tasks import TASKS, make_task, twin_scene

if TYPE_CHECKING:
    from twinrl_sim.cell_view import TwinCell
    from twinrl_sim.spec import SceneSpec


def load_target(target: str, default_episode: int) -> Episode:
    """An episode from ``PATH`` or ``PATH#N``: an .mcap file, a session or a dataset."""
    from twinrl_data.sources import open_episode

    return open_episode(target, default_episode)


def twin_cell(episode: Episode, scene: SceneSpec | None = None) -> TwinCell | None:
    """The cell in 3D for ``episode``: the twin of ``scene`` (a cell of one's own, say a
    seven-joint arm) or else the built-in twin of its task; ``None`` (with the reason
    printed) when there is none or the episode logs no joints it can pose."""
    from twinrl_sim.build import compile_scene
    from twinrl_sim.cell_view import TwinCell

    if scene is None and (episode.meta.task not in TASKS or episode.meta.robot != "ur5e"):
        console.print(
            f"no cell in 3D: the episodes are of {episode.meta.robot or 'an unnamed robot'} "
            f"doing {episode.meta.task or 'an unnamed task'}, not a built-in twin's; "
            "name its twin with --twin"
        )
        return None
    try:
        return TwinCell(
            compile_scene(scene or make_task(episode.meta.task).scene),
            episode.meta.names.get(STATE, []),
            episode.meta.names.get(ENVIRONMENT_STATE, []),
        )
    except ValueError as error:
        console.print(f"no cell in 3D: {error}")
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
    replay: Annotated[
        bool,
        typer.Option(
            help="Also replay the first episode's logged commands in the twin and draw it "
            "as a ghost over it, with how far apart they are."
        ),
    ] = False,
    twin: Annotated[
        Path | None,
        typer.Option(
            help="Scene file of the cell's twin, or a real cell's file (its twin, as its arm "
            "runs it), drawn in 3D and, with --replay, replayed in (a cell of one's own, a "
            "fitted twin; default: the task's built-in twin)."
        ),
    ] = None,
    web: Annotated[
        bool,
        typer.Option(
            help="Serve Rerun's web viewer to browsers instead (a machine without a screen)."
        ),
    ] = False,
    bind: Annotated[
        str, typer.Option(help="Address --web listens on (default: this machine only).")
    ] = "127.0.0.1",
    web_port: Annotated[int, typer.Option(help="Port of --web's page.")] = 9090,
    grpc_port: Annotated[
        int, typer.Option(help="Port --web's page reads the recording from.")
    ] = 9876,
) -> None:
    """Inspect episodes in Rerun; two or more are overlaid on one timeline."""
    from twinrl_data.view import save_rrd, spawn_viewer
    from twinrl_sim.replay import replayed_episode

    if save is not None and save.suffix != ".rrd":
        raise UsageError(f"--save must end in .rrd, got {save}")
    if save is not None and save.exists() and not force:
        raise UsageError(f"--save {save} already exists; choose another path or add --force")
    if web and save is not None:
        raise UsageError("--web serves the episodes and --save writes them; choose one")
    if not web and (bind, web_port, grpc_port) != ("127.0.0.1", 9090, 9876):
        raise UsageError("--bind, --web-port and --grpc-port say where --web listens; add --web")
    if twin is not None and not twin.is_file():
        raise UsageError(f"--twin {twin} does not exist; give a scene or cell file (.yaml)")
    scene = None if twin is None else twin_scene(str(twin))
    episodes = [load_target(t, episode) for t in targets]
    if replay:
        episodes.append(replayed_episode(episodes[0], scene))
    cell = twin_cell(episodes[0], scene)
    if web:
        from twinrl_data.web_view import serve_web

        with serve_web(
            episodes, cell=cell, bind=bind, web_port=web_port, grpc_port=grpc_port
        ) as viewer:
            console.print(f"open {viewer.url} in a browser; Ctrl-C stops serving")
            viewer.wait()
    elif save is not None:
        save_rrd(episodes, save, cell=cell, force=force)
        console.print(f"{save}: {len(episodes)} episode(s), open it with `rerun {save}`")
    else:
        spawn_viewer(episodes, cell=cell)
