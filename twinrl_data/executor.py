"""One way to spread independent jobs over cores: :func:`make_executor`.

Work that scales with cores (twin demo synthesis, the pipeline's real-RL runs) hands
its jobs to an :class:`Executor` instead of opening a pool of its own:

- :class:`InlineExecutor` runs them one after another in this process (one worker:
  no start-up cost, and a debugger sees everything);
- :class:`ProcessExecutor` runs them in spawned worker processes on this machine
  (spawned, not forked, so MuJoCo's GL contexts, torch and threads start clean); the
  workers live as long as the executor, so a worker's caches serve many jobs;
- :class:`~twinrl_data.ray_executor.RayExecutor` runs them as Ray tasks, on a cluster
  (or on Ray embedded here), when the ``cluster`` setting asks for one.

On one machine the process pool is the default: it starts in about a second where Ray
takes several, and runs jobs as fast (``bench/bench_scale.py``), so Ray only pays where
there are more machines.

Work that keeps state between calls (a shard of twin environments) asks the executor
for :mod:`actors <twinrl_data.actors>` instead: one object of a class per worker.

Results come back in job order whatever the number of workers, so a seeded computation
gives the same results on one core or many. A job may send messages (log lines,
progress) to the caller while it runs: ``run`` passes every job a ``send`` callable
and hands what it sends to ``on_message`` as it arrives. The first job that fails
stops the jobs not yet started, and its error is raised in the caller as if the job
had run there. Functions and jobs must be picklable (module-level functions, plain
data), and a script that spawns workers needs an ``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import re
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Protocol, TypeVar

from twinrl_data.actors import Actors, LocalActors, ProcessActors
from twinrl_data.errors import SettingError, TwinrlError

LOCAL = "local"  # the cluster setting's value for Ray embedded on this machine
ADDRESS = re.compile(r"(ray://)?[A-Za-z0-9.\-\[\]:]+:(\d+)")

Job = TypeVar("Job")
Result = TypeVar("Result")
Send = Callable[[Any], None]


class Executor(Protocol):
    """Runs independent jobs; see the module docstring."""

    workers: int

    def map(self, fn: Callable[[Job], Result], jobs: Iterable[Job]) -> list[Result]: ...

    def run(
        self,
        fn: Callable[[Job, Send], Result],
        jobs: Iterable[Job],
        on_message: Callable[[Any], None],
    ) -> list[Result]: ...

    def actors(self, cls: type, inits: list[dict[str, Any]]) -> Actors:
        """One object of ``cls`` per ``inits`` entry (its keyword arguments), each where
        a job would run (:mod:`twinrl_data.actors`)."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Executor: ...

    def __exit__(self, *exc: object) -> None: ...


def cluster_address(cluster: str) -> str | None:
    """Where the ``cluster`` setting runs the jobs, as ``ray.init`` takes it: ``None``
    for this machine's worker processes (the setting empty and ``RAY_ADDRESS`` unset),
    :data:`LOCAL` for Ray embedded here, else the cluster's address."""
    value = cluster.strip() or os.environ.get("RAY_ADDRESS", "").strip()
    if value in ("", "none"):
        return None
    if value in (LOCAL, "auto"):
        return value
    match = ADDRESS.fullmatch(value)
    if match is None or not 0 < int(match.group(2)) < 65536:
        source = "" if cluster.strip() else " (from RAY_ADDRESS)"
        raise SettingError(
            "cluster",
            f"must be none, local, auto, HOST:PORT or ray://HOST:PORT (a Ray cluster's "
            f"head, e.g. ray://head:10001), got '{value}'{source}",
        )
    return value


class InlineExecutor:
    """Every job in this process, in order."""

    workers = 1

    def map(self, fn: Callable[[Job], Result], jobs: Iterable[Job]) -> list[Result]:
        return [fn(job) for job in jobs]

    def run(
        self,
        fn: Callable[[Job, Send], Result],
        jobs: Iterable[Job],
        on_message: Callable[[Any], None],
    ) -> list[Result]:
        return [fn(job, on_message) for job in jobs]

    def actors(self, cls: type, inits: list[dict[str, Any]]) -> Actors:
        return LocalActors(cls, inits)

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self) -> InlineExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_messages: Any = None  # a worker's channel back to the caller (set when it starts)


def _start_worker(messages: Any, initializer: Callable[[], None] | None) -> None:
    global _messages
    _messages = messages
    if initializer is not None:
        initializer()


def _call_with_send(fn: Callable[[Any, Send], Any], job: Any) -> Any:
    return fn(job, _messages.put)


class ProcessExecutor:
    """Jobs in ``workers`` spawned processes; ``initializer`` runs once in each worker
    (e.g. to limit torch to one thread per worker)."""

    def __init__(self, workers: int, *, initializer: Callable[[], None] | None = None) -> None:
        if workers < 1:
            raise TwinrlError(f"an executor needs at least one worker, got {workers}")
        self.workers = workers
        context = multiprocessing.get_context("spawn")
        self._messages = context.Queue()
        self._pool = ProcessPoolExecutor(
            workers,
            mp_context=context,
            initializer=_start_worker,
            initargs=(self._messages, initializer),
        )

    def map(self, fn: Callable[[Job], Result], jobs: Iterable[Job]) -> list[Result]:
        futures = [self._pool.submit(fn, job) for job in jobs]
        return self._gather(futures, None)

    def run(
        self,
        fn: Callable[[Job, Send], Result],
        jobs: Iterable[Job],
        on_message: Callable[[Any], None],
    ) -> list[Result]:
        futures = [self._pool.submit(_call_with_send, fn, job) for job in jobs]
        return self._gather(futures, on_message)

    def _gather(self, futures: list[Future], on_message: Callable[[Any], None] | None) -> list[Any]:
        """Wait for every job, passing messages on; stop the rest at the first failure."""
        while True:
            finished = all(f.done() for f in futures)
            try:
                # Once every job is done, what the workers sent last may still be on its way.
                message = self._messages.get(timeout=0.05 if finished else 0.2)
            except queue.Empty:
                if finished:
                    break
            else:
                if on_message is not None:
                    on_message(message)
            if any(f.done() and f.exception() is not None for f in futures):
                for future in futures:
                    future.cancel()  # jobs under way finish; the others never start
                break
        return [future.result() for future in futures]  # a job's error is raised here

    def actors(self, cls: type, inits: list[dict[str, Any]]) -> Actors:
        return ProcessActors(cls, inits)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ProcessExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_executor(
    workers: int | None,
    *,
    initializer: Callable[[], None] | None = None,
    cluster: str = "",
) -> Executor:
    """An executor with ``workers`` workers (``initializer`` runs in each worker process,
    not in this one). On this machine (``cluster`` empty, ``RAY_ADDRESS`` unset): in this
    process for one worker, processes beyond (``None``: one per core). Else Ray tasks
    where ``cluster`` says (:func:`twinrl_data.ray_executor.cluster_address`; ``None``:
    one per CPU of the cluster)."""
    if workers is not None and workers < 1:
        raise TwinrlError(f"an executor needs at least one worker, got {workers}")
    address = cluster_address(cluster)
    if address is not None:
        from twinrl_data.ray_executor import RayExecutor  # Ray loads only when it runs

        embedded = address == LOCAL
        return RayExecutor(workers, address=None if embedded else address, initializer=initializer)
    workers = workers or os.cpu_count() or 1
    return InlineExecutor() if workers == 1 else ProcessExecutor(workers, initializer=initializer)


def spreading_executor(
    workers: int | None, cluster: str = "", *, initializer: Callable[[], None] | None = None
) -> Executor | None:
    """The executor of work that runs in the caller unless asked to spread: ``None`` for
    one worker, or ``workers`` unset, without a cluster (the caller runs it as it
    would alone); else :func:`make_executor`'s, ``workers`` unset meaning one per CPU
    of the cluster."""
    if cluster_address(cluster) is None and workers in (None, 1):
        return None
    return make_executor(workers, initializer=initializer, cluster=cluster)
