"""``twinrl gap``: where measured episodes and the twin disagree, and which effect
explains it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (rendering, datasets, the fitting) when it runs.
from twinrl_data.atomic import write_text_atomic
from twinrl_data.console import progress
from twinrl_data.errors import UsageError
from twinrl_sim.cli.common import ClusterOption, console
from twinrl_sim.gap.candidates import CANDIDATES, IMAGE_EFFECTS
from twinrl_sim.tasks import TASKS, twin_scene

WindowOption = Annotated[
    int | None,
    typer.Option(
        help="Control steps per shooting window (default: 2 s of the log: 20 at 10 Hz, 250 at "
        "125 Hz).",
        min=2,
    ),
]


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
    window: WindowOption = None,
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
    write_text_atomic(
        out / "localization.json",
        json.dumps(
            {
                "episodes": len(episodes),
                "window": int(max(r.step_in_window.max() for r in replays)),
                "rows": [r.to_dict() for r in rows],
            },
            indent=1,
        ),
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
    window: WindowOption = None,
    noise: Annotated[
        str,
        typer.Option(
            help="Sensor noise per signal family, the residuals' unit, e.g. 'q=2e-4,tau=0.1' "
            "(families: q rad, qd rad/s, tcp m, tau N m, object m, image: standardised grey, "
            "colour: 0-1)."
        ),
    ] = "",
    seed: Annotated[int, typer.Option(help="Seeds the held-out split and window choice.")] = 0,
    fitted_per_round: Annotated[
        int | None,
        typer.Option(
            help="Candidates fitted in full per round, those whose first Gauss-Newton step "
            "explains most (default: the diagnosis's own few; 0: every candidate, "
            "unscreened, slower)."
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Workers for each round's screens and fits (default: 1, in this process; "
            "on a cluster, one per CPU).",
            min=1,
        ),
    ] = None,
    cluster: ClusterOption = "",
) -> None:
    """Name the physical effects the twin lacks: screen every candidate effect on the
    measured episodes (mujoco.sysid over shooting windows) and fit the most promising,
    keep the one that held-out episodes and BIC support, repeat until none is
    significant, and write the fitted twin with a report of the gap before and after."""
    from twinrl_data.sources import discover_episodes
    from twinrl_sim.gap.diagnose import diagnose
    from twinrl_sim.gap.localize import localize
    from twinrl_sim.gap.noise import NoiseFloor
    from twinrl_sim.gap.report import command_lag_line, format_params, write_report
    from twinrl_sim.gap.shooting import replay_windows

    scene = twin_scene(twin)
    noise_floor = NoiseFloor.parse(noise)
    allowed = (
        [e.strip() for e in effects_allowed.split(",") if e.strip()] if effects_allowed else None
    )
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"{out} exists and is not empty; choose another --out")
    images = allowed is None or any(e in allowed for e in IMAGE_EFFECTS)
    episodes = discover_episodes(measured, images=images, samples=True)
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
            **({} if fitted_per_round is None else {"fitted_per_round": fitted_per_round or None}),
            log=lambda message: bar.update(job, description=message),
            workers=workers,
            cluster=cluster,
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
    if diagnosis.command_lag is not None:
        console.print(command_lag_line(diagnosis))
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
