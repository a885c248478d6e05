"""Stateful workers beside the executor's jobs: :class:`Actors`.

A job (:mod:`twinrl_data.executor`) starts from nothing and returns one result. Some
work keeps state between calls: a shard of twin environments steps from where its last
call left it. An executor's :meth:`~twinrl_data.executor.Executor.actors` makes one
object of a class per worker, where its jobs would run, and :meth:`Actors.call` calls
one method on every object at once and returns their results in order:

- :class:`LocalActors`: the objects in this process (one worker);
- :class:`ProcessActors`: each object in a spawned process of its own, spoken to over
  a pipe;
- :class:`~twinrl_data.ray_executor.RayActors`: each a Ray actor, on a cluster or Ray
  embedded here.

An object's error is raised in the caller as it was raised in the worker; a worker that
is gone, or that does not answer within a call's ``timeout_s`` (it is then stopped, as a
worker out of step with its caller is no use), raises :class:`ActorLost`. Classes and
arguments must be picklable, as jobs are.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Sequence
from typing import Any, Protocol

from twinrl_data.errors import TwinrlError

CLOSE_S = 30.0  # s an object's close may take before its worker is stopped regardless


class Actors(Protocol):
    """One object per worker; see the module docstring."""

    def call(self, method: str, args: Sequence[tuple], timeout_s: float | None = None) -> list[Any]:
        """``method`` of every object at once, object ``i`` with ``args[i]``; the results
        in order. Without an answer from every worker within ``timeout_s`` (None: no
        limit) the workers are stopped and :class:`ActorLost` raised."""
        ...

    def close(self) -> None:
        """Close every object (its ``close`` method, if it has one) and stop its worker."""
        ...


class ActorLost(TwinrlError):
    """An actor's worker is gone (its process died, its node left): the object and its
    state in memory with it. Errors the object itself raised are raised as they were."""


def check_arguments(count: int, args: Sequence[tuple]) -> None:
    """Refuse a call whose argument tuples are not one per actor."""
    if len(args) != count:
        raise TwinrlError(
            f"a call to {count} actors needs {count} argument tuples, got {len(args)}"
        )


class LocalActors:
    """The objects in this process, called one after another (a call here cannot be
    timed out: it is this process's own work)."""

    def __init__(self, cls: type, inits: Sequence[dict[str, Any]]) -> None:
        self.objects = [cls(**init) for init in inits]

    def call(self, method: str, args: Sequence[tuple], timeout_s: float | None = None) -> list[Any]:
        check_arguments(len(self.objects), args)
        return [getattr(o, method)(*a) for o, a in zip(self.objects, args, strict=True)]

    def close(self) -> None:
        for obj in self.objects:
            getattr(obj, "close", lambda: None)()


def _serve(connection: Any, cls: type, init: dict[str, Any]) -> None:
    """A worker process's loop: make the object, then answer calls until told to stop."""
    try:
        obj = cls(**init)
    except BaseException as error:  # handed to the caller at its first call
        connection.send(("error", error))
        return
    connection.send(("ok", None))
    while (message := connection.recv()) is not None:
        method, args = message
        try:
            connection.send(("ok", getattr(obj, method)(*args)))
        except BaseException as error:
            connection.send(("error", error))
    getattr(obj, "close", lambda: None)()
    connection.send(("ok", None))


class ProcessActors:
    """Each object in a spawned process of its own (spawned, as the executor's workers
    are, so MuJoCo's GL contexts and torch start clean)."""

    def __init__(
        self, cls: type, inits: Sequence[dict[str, Any]], timeout_s: float | None = None
    ) -> None:
        """Start the objects; past ``timeout_s`` for any of them to be made, every worker
        is stopped (:class:`ActorLost`)."""
        context = multiprocessing.get_context("spawn")
        self._pipes, self._processes = [], []
        for init in inits:
            ours, theirs = context.Pipe()
            process = context.Process(target=_serve, args=(theirs, cls, init), daemon=True)
            process.start()
            theirs.close()
            self._pipes.append(ours)
            self._processes.append(process)
        try:
            self._answers("its start", timeout_s)  # every object made, or the first error
        except BaseException:
            self.close()
            raise

    def _answers(self, method: str = "", timeout_s: float | None = None) -> list[Any]:
        """One answer from every worker (all read, so the pipes stay in step); the first
        error is raised. Past ``timeout_s`` every worker is stopped."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        answers = []
        for pipe, process in zip(self._pipes, self._processes, strict=True):
            if deadline is not None and not pipe.poll(max(0.0, deadline - time.monotonic())):
                pid = process.pid
                self._stop()  # out of step with its caller: of no more use
                raise ActorLost(
                    f"actor process {pid} did not answer {method} within {timeout_s:g} s; "
                    "it was stopped"
                )
            try:
                answers.append(pipe.recv())
            except (EOFError, OSError):
                answers.append(("error", ActorLost(f"actor process {process.pid} died")))
        for status, value in answers:
            if status == "error":
                raise value
        return [value for _, value in answers]

    def call(self, method: str, args: Sequence[tuple], timeout_s: float | None = None) -> list[Any]:
        if not self._processes:
            raise ActorLost("these actors' processes were stopped; start new ones")
        check_arguments(len(self._pipes), args)
        for pipe, a, process in zip(self._pipes, args, self._processes, strict=True):
            try:
                pipe.send((method, tuple(a)))
            except OSError:
                raise ActorLost(f"actor process {process.pid} died") from None
        return self._answers(method, timeout_s)

    def close(self) -> None:
        for pipe, process in zip(self._pipes, self._processes, strict=True):
            if process.is_alive():
                try:
                    pipe.send(None)
                    if pipe.poll(CLOSE_S):
                        pipe.recv()
                except (EOFError, BrokenPipeError, OSError):
                    pass
        self._stop(wait=10.0)

    def _stop(self, wait: float = 0.0) -> None:
        """End every worker, killed when it has not ended within ``wait`` s, and its pipe."""
        for pipe, process in zip(self._pipes, self._processes, strict=True):
            process.join(timeout=wait)
            if process.is_alive():
                process.kill()
                process.join(timeout=10)
            pipe.close()
        self._pipes, self._processes = [], []
