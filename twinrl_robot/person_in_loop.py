"""The person at a cell during real RL: their device takes the controls from the policy
and hands them back, their keys (or the device's buttons) mark an episode's success or
failure and pause the run, and on a real cell they set each reset up and start it.

Keys, whatever the device: ``s`` success, ``f`` failure (the episode ends there), ``q``
pause (the run stops after this episode, everything kept; ``--resume`` goes on), Enter
starts an episode once the cell is set up (a real cell only: the plant and the emulator
set themselves up).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from twinrl_robot.errors import RobotError
from twinrl_robot.loop import Judge
from twinrl_robot.recording import SET_UP, Marks, check_device, wait_for_start
from twinrl_robot.teleop.teleop import Teleop, TeleopOperator
from twinrl_robot.teleop.terminal import TerminalKeys


class RunPaused(RobotError):
    """The person paused the run before an episode started."""


class PersonInLoop:
    """A person's device, keys and set-up around the RL loop's episodes.

    Args:
        teleop: their device (``None``: nobody takes the controls).
        terminal: the terminal's keys (``None``: the device's buttons only).
        sets_up: whether the person sets each reset up and starts the episode (a real
            cell), or the cell does it itself (the plant, the emulator).
        on_wait: told what the person is waited for, while they set the cell up.
    """

    def __init__(
        self,
        teleop: Teleop | None,
        terminal: TerminalKeys | None,
        *,
        sets_up: bool,
        on_wait: Callable[[str], None] | None = None,
    ) -> None:
        self.teleop = teleop
        self.operator = TeleopOperator(teleop) if teleop is not None else None
        self.marks = Marks(terminal)
        self.sets_up, self.on_wait = sets_up, on_wait
        self.pause_requested = False
        self.marked: str | None = None  # this episode's success or failure mark

    def begin(self) -> None:
        """A new episode: no mark yet."""
        self.marked = None

    def ready(
        self, observation: dict[str, np.ndarray], showing: Callable[[], None] | None = None
    ) -> None:
        """On a real cell, wait until the person has set the reset up and starts
        (``showing``: called while waiting, e.g. to show the live cameras)."""
        if not self.sets_up:
            return

        def waiting() -> None:
            if self.on_wait is not None:
                self.on_wait(SET_UP)
            if showing is not None:
                showing()

        if not wait_for_start(self.teleop, self.marks, waiting):
            self.pause_requested = True
            raise RunPaused("paused by the person before the episode started")

    def key_judge(self, observation: dict[str, np.ndarray]) -> bool:
        """The person's success mark ends the episode as a success."""
        self.poll()
        return self.marked == "success"

    def watching(self, judge: Judge) -> Judge:
        """``judge``, with the person's marks and pause collected at every step."""

        def judged(observation: dict[str, np.ndarray]) -> bool:
            self.poll()
            return judge(observation)

        return judged

    def until(self) -> bool:
        """The person's failure mark ends the episode as a failure."""
        return self.marked == "failure"

    def poll(self) -> None:
        """Take the person's marks so far (the device's buttons, the keys)."""
        if self.operator is not None:
            check_device(self.operator.teleop)
            self.marks.add(self.operator.take_events())
        while (mark := self.marks.take()) is not None:
            if mark == "quit":
                self.pause_requested = True
            elif mark in ("success", "failure") and self.marked is None:
                self.marked = mark

    def close(self) -> None:
        if self.teleop is not None:
            self.teleop.close()
