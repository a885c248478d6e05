"""Real-time scheduling: the loop's thread at the cell's SCHED_FIFO priority while it
runs and the threads it starts at the normal policy, and a host that may not give it
refused in one line before the arm moves (on the emulated arm: test_ur_cell.py)."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest
import yaml

from tests.robot.test_cell_file import EXAMPLE
from tests.robot.test_loop import Scripted
from tests.test_cli import twinrl
from twinrl_robot.backends import open_robot
from twinrl_robot.cell_file import CellFileError, parse_cell
from twinrl_robot.errors import RobotError
from twinrl_robot.loop import run_episode
from twinrl_robot.realtime import check_realtime, realtime_thread
from twinrl_robot.wrappers.base import layers
from twinrl_sim.tasks import make_task


def thread_policy(thread_id: int = 0) -> int:
    """A thread's scheduling policy, without the reset-on-fork flag."""
    return os.sched_getscheduler(thread_id) & ~os.SCHED_RESET_ON_FORK


def _may_take_realtime() -> bool:
    try:
        check_realtime(1)
    except RobotError:
        return False
    return True


needs_realtime = pytest.mark.skipif(
    not _may_take_realtime(), reason="this process may not take a SCHED_FIFO priority"
)


@needs_realtime
def test_a_thread_holds_the_priority_inside_and_threads_it_starts_stay_normal():
    started = []
    with realtime_thread(7):
        assert thread_policy() == os.SCHED_FIFO and os.sched_getparam(0).sched_priority == 7
        thread = threading.Thread(target=lambda: started.append(thread_policy()))
        thread.start()
        thread.join()
    assert started == [os.SCHED_OTHER]
    assert thread_policy() == os.SCHED_OTHER
    with realtime_thread(None):
        assert thread_policy() == os.SCHED_OTHER


def test_a_host_that_may_not_give_the_priority_is_refused_in_one_line(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with pytest.raises(RobotError) as error:
        check_realtime(80)
    message = str(error.value)
    assert "real-time priority 80 (arm.realtime_priority)" in message
    assert "rtprio" in message and "\n" not in message
    check_realtime(None)  # none asked: nothing to refuse


def test_the_cell_file_bounds_the_priority_and_cell_check_says_whether_it_is_allowed(tmp_path):
    data = yaml.safe_load(EXAMPLE.read_text())
    for bad in (0, 100, 1.5):
        data["arm"]["realtime_priority"] = bad
        with pytest.raises(CellFileError, match="realtime_priority"):
            parse_cell(data)
    data["arm"]["realtime_priority"] = 80
    assert parse_cell(data).arm.realtime_priority == 80
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    result = twinrl("cell", "check", str(path))
    assert result.returncode == 0, result.stderr
    expected = "this host allows it" if _may_take_realtime() else "refused on this host"
    assert "SCHED_FIFO priority 80" in result.stdout and expected in result.stdout


@needs_realtime
def test_the_loop_runs_at_the_backends_priority_and_returns_to_normal_after():
    task = make_task("pick_place")
    config = task.sample_config(np.random.default_rng(0), "ID")
    robot = open_robot("twin", task)
    *_, backend = layers(robot)
    backend.loop_priority = 5  # what a real cell's arm.realtime_priority gives
    seen = []
    try:
        run_episode(
            robot, Scripted([np.zeros(7, np.float32)] * 3), task, config, judge=None,
            max_steps=3,
            on_step=lambda t, sent: seen.append(
                (thread_policy(), os.sched_getparam(0).sched_priority)
            ),
        )  # fmt: skip
    finally:
        robot.close()
    assert seen == [(os.SCHED_FIFO, 5)] * 3
    assert thread_policy() == os.SCHED_OTHER
