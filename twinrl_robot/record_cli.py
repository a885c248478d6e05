"""``twinrl record``: record episodes with a person at a teleop device."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from twinrl_data.session import Session
from twinrl_data.settings_cli import options, settings_function
from twinrl_robot.record_settings import RecordSettings

console = Console(soft_wrap=True)


def _status_line(status) -> str:
    gb = status.disk_free / 2**30
    kept = f"{status.saved} kept" + (f", {status.discarded} discarded" if status.discarded else "")
    last = f" | last: {status.last}" if status.last else ""
    return (
        f"episode {status.episode}/{status.episodes} | {status.state} | {status.elapsed:5.1f} s | "
        f"{status.frames} frames | {status.dropped} dropped | {gb:.1f} GiB free | {kept}{last}\n"
        "[dim]Enter start  s success  f failure  d discard  n note  q stop[/dim]"
    )


def _record(settings: dict[str, Any]) -> None:
    from twinrl_robot.recording import run_recording

    config = RecordSettings(**settings)
    out = config.out
    try:
        with Live(console=console, auto_refresh=False, transient=True) as live:
            report = run_recording(
                config,
                on_status=lambda status: live.update(
                    Text.from_markup(_status_line(status)), refresh=True
                ),
                on_web=lambda url: console.print(f"live view: open {url} in a browser"),
            )
    except KeyboardInterrupt:  # an episode under way is kept, marked aborted (run_episode)
        kept = len(Session(out).episode_paths()) if Path(out).is_dir() else 0
        console.print(
            f"stopped (Ctrl-C): {out} holds {kept} episode(s), one cut short marked aborted; "
            "run the same command to continue the session"
        )
        raise SystemExit(130) from None
    table = Table("episode", "outcome", "steps", "note", title=f"recorded into {out}")
    for episode in report.episodes:
        table.add_row(
            Path(episode.path).name, episode.outcome, str(episode.steps), episode.note or ""
        )
    console.print(table)
    if report.recovered:
        console.print(f"recovered first: {', '.join(Path(p).name for p in report.recovered)}")
    if report.discarded:
        console.print(f"discarded (kept in {out}/discarded): {len(report.discarded)}")
    console.print(
        f"inspect: twinrl view {out}  |  for learning: twinrl data export {out} --to DATASET"
    )


# ``twinrl record``: its options derive from RecordSettings (all but the scripted
# person's marks, which tests give).
record = settings_function(
    "record",
    options(RecordSettings, only=[f for f in RecordSettings.__dataclass_fields__ if f != "marks"]),
    _record,
    help="Record episodes with a person at a teleop device: reset guidance, live view, "
    "marks.\n\nEach episode: set the cell up as the live view shows, press Enter (or the "
    "device's start button), drive, then s (success), f (failure) or d (discard and "
    "record again); n types a note, q stops. Every episode is on disk as it is "
    "recorded; run the same command again to continue a session (a crash's partial "
    "episode is recovered first).",
)
