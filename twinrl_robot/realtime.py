"""Real-time scheduling for the robot loop's thread.

A cell's host shares its cores between the robot loop, the cameras' decoding and the
recorder's encoding; under Linux's normal policy a control period may then end a few
milliseconds late (docs/benchmarks.md, "Recording at a real cell's rates"). A thread at
a ``SCHED_FIFO`` priority runs the moment its sleep ends, ahead of every normal thread,
as ur_rtde's ``rt_priority`` and ros2_control's loops do. The cell file's
``arm.realtime_priority`` gives it to the robot loop's thread while an episode runs.
Threads the loop's thread starts keep the normal policy (``SCHED_RESET_ON_FORK``), so
the recorder's and the cameras' threads stay below it.

The controller link's process keeps the normal policy: with its servo stream's thread,
or all its threads, at the priority and the host pinned to one core, the emulator's
watchdog stopped the program before the first episode every time (likely ur_rtde's
waits for the controller's answers, which need its receiving thread to run beside a
real-time thread on the same core).

Taking a priority needs root, ``CAP_SYS_NICE`` or an ``rtprio`` limit
(``/etc/security/limits.conf``); :func:`check_realtime` says so in one line before the
arm moves.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from twinrl_robot.errors import RobotError


def _refusal(priority: int, why: str) -> RobotError:
    return RobotError(
        f"the cell asks real-time priority {priority} (arm.realtime_priority) and {why}: "
        "run as root, give the user an rtprio limit (/etc/security/limits.conf) or "
        "CAP_SYS_NICE, or leave arm.realtime_priority out"
    )


def _set(priority: int) -> None:
    """The calling thread at SCHED_FIFO ``priority``; threads it starts stay normal."""
    if not hasattr(os, "sched_setscheduler"):
        raise _refusal(priority, f"{sys.platform} has no SCHED_FIFO (Linux has)")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
    except PermissionError:
        raise _refusal(priority, "this process may not take it") from None


def check_realtime(priority: int | None) -> None:
    """Refuse in one line a priority this process may not take (``None``: none asked);
    the calling thread's own policy is left as it was."""
    if priority is None:
        return
    with realtime_thread(priority):
        pass


def realtime_note(priority: int) -> str:
    """Whether this process may take ``priority``, in words (``twinrl cell check``)."""
    try:
        check_realtime(priority)
    except RobotError as err:
        return f"SCHED_FIFO priority {priority}, refused on this host: {err}"
    return f"SCHED_FIFO priority {priority} (this host allows it)"


@contextmanager
def realtime_thread(priority: int | None) -> Iterator[None]:
    """The calling thread at SCHED_FIFO ``priority`` while inside, its own policy again
    after (``None``: nothing changes); threads started inside keep the normal policy."""
    if priority is None:
        yield
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    _set(priority)
    try:
        yield
    finally:
        os.sched_setscheduler(0, policy, param)
