"""Recording sessions with a person at a teleop device: ``twinrl record``.

Per episode: the configuration to set up comes from the reset plan and is shown in the
live view (the twin's render, the objects' outlines over the live camera); the arm goes
to its start pose (the plant and the emulator set the objects up themselves); the
person starts the episode (Enter, or the device's ``start`` button), drives, and marks
it: **success**, **failure**, or **discard** (the episode leaves the session for
``discarded/`` and the same configuration is recorded again); ``n`` types a note kept
with the episode; ``q`` stops the session (the episode so far is kept, marked as
stopped). An episode that reaches the task's step limit ends as a failure.

Nothing recorded is lost to a crash: frames stream into the episode's MCAP file (a
killed recorder loses at most the last second), the session's manifest is updated when
each episode starts and ends, and recording again into the same folder first recovers
an episode a crash left open, then goes on numbering after it.
"""

from __future__ import annotations

import queue
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from twinrl_data.interrupts import interruptible
from twinrl_data.recorder import Recorder
from twinrl_data.repair import repair_session
from twinrl_data.schema import ENVIRONMENT_STATE, STATE
from twinrl_data.session import Session
from twinrl_data.web_view import start_web_viewer
from twinrl_robot.errors import RobotError
from twinrl_robot.live_view import LiveView
from twinrl_robot.loop import run_episode, sensor_counts
from twinrl_robot.record_settings import RecordSettings
from twinrl_robot.reset_plan import ResetPlan
from twinrl_robot.robot import Robot, Sent
from twinrl_robot.teleop.device import TeleopError
from twinrl_robot.teleop.teleop import Teleop, TeleopSource
from twinrl_robot.teleop.terminal import TerminalKeys
from twinrl_sim.tasks import Task, TaskConfig

MARK_KEYS = {
    "enter": "start",
    "s": "success",
    "f": "failure",
    "d": "discard",
    "n": "note",
    "q": "quit",
}
"""The terminal's keys for the recording's marks, whatever the device."""
SET_UP = "set up the cell as shown, then start (Enter)"
WAIT_PERIOD = 0.1  # s between looks at the device and the cameras while the cell is set up
DISK_PERIOD = 1.0  # s between looks at the free disk space for the status line


class RecordingStopped(RobotError):
    """The person stopped the session (``q``)."""


@dataclass
class RecordStatus:
    """What the status line shows."""

    episode: int  # 1-based, of this session's run
    episodes: int
    state: str  # "set up the cell, then start", "recording", "typing a note: ..."
    elapsed: float = 0.0  # s of the current episode
    frames: int = 0
    dropped: int = 0  # camera frames dropped this episode
    disk_free: int = 0  # bytes
    saved: int = 0  # episodes kept so far in this run
    discarded: int = 0
    last: str = ""  # how the last episode ended


@dataclass(frozen=True)
class RecordedEpisode:
    path: str
    outcome: str  # success, failure, stopped
    steps: int
    note: str | None


@dataclass(frozen=True)
class RecordReport:
    episodes: tuple[RecordedEpisode, ...]
    discarded: tuple[str, ...]
    recovered: tuple[str, ...]  # episodes a crash had left open, recovered first


@dataclass
class Marks:
    """The person's marks from the device's buttons and the terminal's keys; ``n``
    starts a note, typed until Enter."""

    terminal: TerminalKeys | None
    pending: list[str] = field(default_factory=list)
    note: str | None = None
    typing: str | None = None  # the note being typed

    def __post_init__(self) -> None:
        self.keys = self.terminal.subscribe() if self.terminal is not None else None

    def add(self, events: list[str]) -> None:
        for event in events:
            if event == "note":
                self._start_note()
            elif event in MARK_KEYS.values():
                self.pending.append(event)

    def poll(self) -> None:
        while self.keys is not None:
            try:
                key, _ = self.keys.get_nowait()
            except queue.Empty:
                return
            if self.typing is not None:
                self._type(key)
            elif key in MARK_KEYS:
                self.add([MARK_KEYS[key]])

    def _start_note(self) -> None:
        self.typing = ""
        if self.terminal is not None:
            self.terminal.typing = True

    def _type(self, key: str) -> None:
        assert self.typing is not None
        if key == "enter":
            self.note = " ".join(filter(None, [self.note, self.typing.strip()])) or None
            self.typing = None
        elif key == "backspace":
            self.typing = self.typing[:-1]
        elif key == "esc":
            self.typing = None
        elif key == "space":
            self.typing += " "
        elif len(key) == 1:
            self.typing += key
        else:
            return
        if self.terminal is not None:
            self.terminal.typing = self.typing is not None

    def take(self) -> str | None:
        """The next mark (a note is handled here and not returned)."""
        self.poll()
        return self.pending.pop(0) if self.pending else None


def record_session(
    robot: Robot,
    task: Task,
    teleop: Teleop,
    session: Session,
    *,
    episodes: int,
    plan: ResetPlan,
    terminal: TerminalKeys | None = None,
    view: LiveView | None = None,
    on_status: Callable[[RecordStatus], None] | None = None,
    operator: str | None = None,
    max_steps: int | None = None,
    settle: int = 3,
) -> RecordReport:
    """Record ``episodes`` kept episodes of ``task`` driven by ``teleop`` into ``session``
    (see the module docstring). A simulated ``robot`` is paced at its control rate, as
    a person drives it; a real one keeps its rate itself. After a success mark the arm
    holds for ``settle`` more recorded steps (what a reward classifier learns from)."""
    if episodes < 1:
        raise RobotError(f"episodes must be at least 1, got {episodes}")
    recovered = tuple(str(p) for p in repair_session(session.path).recovered)
    session.refresh()
    take = _EpisodeTaker(robot, task, teleop, terminal, view, on_status, session)
    recorder = Recorder(session)
    kept: list[RecordedEpisode] = []
    discarded: list[str] = []
    index = len(session.entries)  # a continued session's plan goes on after its episodes
    while len(kept) < episodes:
        planned = plan.reset(index)
        take.begin(len(kept) + 1, episodes, planned.config)
        meta = task.episode_meta(
            source="teleop",
            world=robot.world,
            names=robot.names,
            config=planned.config,
            region=planned.region,
            operator=operator or teleop.kind,
        )
        try:
            result = run_episode(
                robot,
                take.source,
                task,
                planned.config,
                judge=take.judge,
                recorder=recorder,
                meta=meta,
                max_steps=max_steps,
                on_step=take.on_step,
                until=take.until,
                ready=take.ready,
                note=lambda: take.marks.note,
                settle=settle,
            )
        except RecordingStopped:
            if take.recording and recorder.saved_path is not None:
                path, note = str(recorder.saved_path), take.marks.note
                kept.append(RecordedEpisode(path, "stopped", take.status.frames, note))
            break
        note, take.marks.note = take.marks.note, None
        assert result.path is not None
        if take.mark == "discard":
            discarded.append(str(session.discard(result.path)))
            take.show(discarded=len(discarded), last="discarded: recording it again")
            continue
        label = "success" if result.success else "failure"
        kept.append(RecordedEpisode(str(result.path), label, result.steps, note))
        index += 1
        take.show(saved=len(kept), last=f"episode {len(kept)}: {label}, {result.steps} steps")
    return RecordReport(tuple(kept), tuple(discarded), recovered)


class _EpisodeTaker:
    """The hooks one recorded episode runs with: the person's start, marks, pacing,
    the live view and the status line."""

    def __init__(
        self,
        robot: Robot,
        task: Task,
        teleop: Teleop,
        terminal: TerminalKeys | None,
        view: LiveView | None,
        on_status: Callable[[RecordStatus], None] | None,
        session: Session,
    ) -> None:
        self.robot, self.task, self.teleop, self.view = robot, task, teleop, view
        self.on_status, self.session = on_status, session
        self.source = TeleopSource(teleop)
        self.marks = Marks(terminal)
        self.simulated = robot.world in ("plant", "twin")
        self.period = 1.0 / robot.control_hz
        self.status = RecordStatus(0, 0, "")
        self.mark: str | None = None
        self.recording = False
        self._disk_checked = -np.inf

    def begin(self, episode: int, episodes: int, config: TaskConfig) -> None:
        self.config, self.mark, self.recording = config, None, False
        self.show(
            episode=episode,
            episodes=episodes,
            elapsed=0.0,
            frames=0,
            dropped=0,
            state="the arm goes to its start pose",
        )

    def show(self, **changes: Any) -> None:
        now = time.monotonic()
        if now - self._disk_checked >= DISK_PERIOD:
            changes["disk_free"] = shutil.disk_usage(self.session.path).free
            self._disk_checked = now
        self.status = replace(self.status, **changes)
        if self.marks.typing is not None:
            self.status.state = f"typing a note (Enter keeps it): {self.marks.typing}"
        elif self.recording:
            self.status.state = "recording"
        if self.on_status is not None:
            self.on_status(self.status)

    def ready(self, observation: dict[str, np.ndarray]) -> None:
        """Show the guidance and wait for the person to start."""
        if self.view is not None:
            self.view.guidance(self.status.episode, self.config, observation)

        def waiting() -> None:
            self.show(state=SET_UP)
            if self.view is not None:
                self.view.live(self.robot.observe())

        if not wait_for_start(self.teleop, self.marks, waiting):
            raise RecordingStopped("stopped by the person before the episode started")
        self.started = self.paced = time.monotonic()
        self.recording = True
        self.show()

    def judge(self, _observation: dict[str, np.ndarray]) -> bool:
        """The person's mark: success ends the episode (failure and discard: :meth:`until`)."""
        self.marks.add(self.source.take_events())
        mark = self.marks.take()
        if mark == "quit":
            raise RecordingStopped("stopped by the person (q)")
        if mark in ("success", "failure", "discard"):
            self.mark = mark
        return mark == "success"

    def until(self) -> bool:
        check_device(self.teleop)
        return self.mark in ("failure", "discard")

    def on_step(self, t: int, sent: Sent) -> None:
        if self.view is not None and self.source.observation is not None:
            self.view.step(self.source.observation, sent)
        if self.simulated:  # a person drives at the control rate
            self.paced += self.period
            time.sleep(max(0.0, self.paced - time.monotonic()))
        self.show(
            elapsed=time.monotonic() - self.started, frames=t + 1, dropped=_dropped(self.robot)
        )


def check_device(teleop: Teleop) -> None:
    """Raise the device's :class:`TeleopError` once it is gone."""
    if teleop.lost is not None:
        raise TeleopError(teleop.lost)


def wait_for_start(teleop: Teleop | None, marks: Marks, waiting: Callable[[], None]) -> bool:
    """Wait while the person sets the cell up (``waiting`` is called every
    :data:`WAIT_PERIOD`): ``True`` at their start (Enter, the device's ``start``),
    ``False`` at their quit."""
    while True:
        if teleop is not None:
            check_device(teleop)
            marks.add(list(teleop.step(None).events))
        mark = marks.take()
        if mark in ("start", "quit"):
            return mark == "start"
        waiting()
        time.sleep(WAIT_PERIOD)


def _dropped(robot: Robot) -> int:
    return int(sum(c.get("dropped", 0) for c in sensor_counts(robot).values()))


def run_recording(
    settings: RecordSettings,
    on_status: Callable[[RecordStatus], None] | None = None,
    on_web: Callable[[str], None] | None = None,
) -> RecordReport:
    """``twinrl record``: open the cell (the plant, or the UR arm of the settings' cell
    file, on the emulator when ``emulated``), the session folder (continued when it
    exists), the terminal's keys (when standard input is a terminal and ``keys``), the
    teleop device and the live view (served to browsers when ``web``), and record (see
    :func:`record_session`); ``on_status`` gets the status line's contents as they
    change, ``on_web`` the web viewer's page once it is served."""
    from twinrl_robot.backends import ROBOTS, open_robot, recorded_cameras
    from twinrl_robot.cell_file import CellFile, load_cell
    from twinrl_robot.teleop import open_teleop
    from twinrl_sim.tasks import make_task, task_on_twin

    world = ROBOTS[settings.robot]
    cell_file: CellFile | None = None
    if settings.cell is not None:
        cell_file = load_cell(settings.cell)
        task = make_task(settings.task, task_on_twin(settings.task, cell_file.twin))
    else:
        task = make_task(settings.task)
    reset_plan = ResetPlan(task, settings.plan, seed=settings.seed)
    cameras = recorded_cameras(world, cell_file)
    opened: list[Any] = []
    try:
        view = settings.view
        if settings.web:  # first: a port in use stops it before a session or the arm
            web = start_web_viewer(
                bind=settings.bind, web_port=settings.web_port, grpc_port=settings.grpc_port
            )
            opened.append(web)
            view = web.grpc_url
            if on_web is not None:
                on_web(web.url)
        session = Session.create(settings.out, exist_ok=True)
        terminal = TerminalKeys() if settings.keys and sys.stdin.isatty() else None
        if terminal is not None:
            opened.append(terminal)
        arm = open_robot(
            world,
            task,
            effects=settings.effects,
            seed=settings.seed,
            cameras=cameras,
            effort=True,
            object_poses=world == "plant" or settings.emulated,
            cell=cell_file,
            emulated=settings.emulated,
        )
        opened.append(arm)
        spec = cell_file.teleop if cell_file is not None else None
        device = open_teleop(
            settings.teleop,
            spec,
            terminal=terminal,
            privileged=arm.privileged,
            seed=settings.seed,
            marks=settings.marks,
        )
        opened.append(device)
        live = None
        if view is not None:
            live = LiveView(
                view,
                task,
                cameras,
                arm.names.get(STATE, []),
                environment_names=arm.names.get(ENVIRONMENT_STATE, []),
            )
            opened.append(live)
        with interruptible():  # Ctrl-C stops it even as a script's background job
            return record_session(
                arm,
                task,
                device,
                session,
                episodes=settings.episodes,
                plan=reset_plan,
                terminal=terminal,
                view=live,
                on_status=on_status,
                max_steps=settings.max_steps,
                settle=settings.settle,
            )
    finally:
        for thing in reversed(opened):
            thing.close()
