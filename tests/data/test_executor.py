"""The executor: jobs in order, messages as they come, the first failure raised."""

import os
import time

import pytest

from twinrl_data.errors import SettingError
from twinrl_data.executor import InlineExecutor, ProcessExecutor, cluster_address, make_executor


def square(n):
    return n * n, os.getpid()


def chatty(n, send):
    send(f"job {n} starts")
    if n == 3:
        raise ArithmeticError(f"job {n} cannot")
    return n + 100


def test_jobs_come_back_in_order_inline_or_in_worker_processes():
    with make_executor(1) as inline:
        assert isinstance(inline, InlineExecutor)
        assert [r for r, _ in inline.map(square, range(5))] == [0, 1, 4, 9, 16]
    with make_executor(2) as pool:
        assert isinstance(pool, ProcessExecutor) and pool.workers == 2
        results = pool.map(square, range(8))
        again = pool.map(square, range(3))  # the same workers serve a second call
    assert [r for r, _ in results] == [n * n for n in range(8)]
    assert os.getpid() not in {pid for _, pid in results + again}


@pytest.mark.parametrize("workers", [1, 2])
def test_messages_arrive_and_the_first_failure_is_raised_as_it_was(workers):
    heard = []
    with make_executor(workers) as executor:
        assert executor.run(chatty, [0, 1, 2], heard.append) == [100, 101, 102]
        assert sorted(heard) == [f"job {n} starts" for n in range(3)]
        with pytest.raises(ArithmeticError, match="job 3 cannot"):
            executor.run(chatty, [3, 4], heard.append)
    with pytest.raises(ValueError, match="at least one worker"):
        make_executor(0)


def test_the_cluster_setting_names_where_jobs_run(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert cluster_address("") is None and cluster_address("none") is None
    for value in ("local", "auto", "10.0.0.5:6379", "ray://head.lab:10001", "[::1]:6379"):
        assert cluster_address(value) == value
    monkeypatch.setenv("RAY_ADDRESS", "ray://head:10001")
    assert cluster_address("") == "ray://head:10001"
    assert cluster_address("none") is None  # the setting wins over the environment
    monkeypatch.setenv("RAY_ADDRESS", "head")
    with pytest.raises(SettingError, match=r"cluster must be .* got 'head' \(from RAY_ADDRESS\)"):
        make_executor(2)
    for bad in ("head", "http://head:8265", "ray://head:70000"):
        with pytest.raises(SettingError, match=f"got '{bad}'$"):
            cluster_address(bad)


class Counter:
    """A stateful object for the actors: it remembers what it was told."""

    def __init__(self, start: int) -> None:
        if start < 0:
            raise ArithmeticError(f"cannot start at {start}")
        self.total, self.closed = start, False

    def add(self, n: int) -> tuple[int, int]:
        if n == 13:
            raise ArithmeticError("13 is not added")
        self.total += n
        return self.total, os.getpid()

    def close(self) -> None:
        self.closed = True


@pytest.mark.parametrize("workers", [1, 2])
def test_actors_keep_their_state_between_calls_and_raise_as_raised(workers):
    with make_executor(workers) as executor:
        actors = executor.actors(Counter, [{"start": 0}, {"start": 100}])
        assert [t for t, _ in actors.call("add", [(1,), (2,)])] == [1, 102]
        totals = actors.call("add", [(10,), (20,)])
        assert [t for t, _ in totals] == [11, 122]
        pids = {pid for _, pid in totals}
        assert (pids == {os.getpid()}) if workers == 1 else (len(pids) == 2)
        with pytest.raises(ArithmeticError, match="13 is not added"):
            actors.call("add", [(13,), (1,)])
        # Still in step after a failure (whether the others' calls ran is not said).
        assert actors.call("add", [(0,), (0,)])[0][0] == 11
        with pytest.raises(ValueError, match="needs 2 argument tuples"):
            actors.call("add", [(1,)])
        actors.close()
        with pytest.raises(ArithmeticError, match="cannot start at -1"):
            executor.actors(Counter, [{"start": 1}, {"start": -1}])


class Sleeper:
    """An actor whose calls take as long as they are told."""

    def nap(self, seconds: float) -> float:
        time.sleep(seconds)
        return seconds


def test_an_actor_that_does_not_answer_in_time_is_stopped_and_taken_for_lost():
    from twinrl_data.actors import ActorLost, ProcessActors

    actors = ProcessActors(Sleeper, [{}, {}])
    try:
        assert actors.call("nap", [(0.0,), (0.1,)], timeout_s=30) == [0.0, 0.1]
        processes = list(actors._processes)
        started = time.monotonic()
        with pytest.raises(ActorLost, match=r"did not answer nap within 0.5 s; it was stopped"):
            actors.call("nap", [(0.0,), (60.0,)], timeout_s=0.5)
        assert time.monotonic() - started < 30  # not the minute the call would have taken
        assert not any(p.is_alive() for p in processes)
        with pytest.raises(ActorLost):  # nothing left to call
            actors.call("nap", [], timeout_s=1)
    finally:
        actors.close()
