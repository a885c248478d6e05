"""The executor on Ray: :class:`RayExecutor` runs jobs as Ray tasks, on this machine or a
cluster, with the same contract as the process pool (:mod:`twinrl_data.executor`).

Where it runs is the ``cluster`` setting (:func:`twinrl_data.executor.cluster_address`):

- ``local`` (``address`` ``None``): Ray embedded in this process, started for the
  executor and stopped with it. Every one of its servers listens on the loopback
  interface only and no dashboard or job API starts, since whoever reaches a Ray node
  may run code on it.
- ``auto``: the cluster this machine joined (``ray start``), or the one ``RAY_ADDRESS``
  names; ``HOST:PORT``: a cluster's head from a machine of the cluster; ``ray://HOST:PORT``:
  a cluster's head through Ray Client, from anywhere.

A cluster should use Ray's token authentication (``RAY_AUTH_MODE=token``, the same
token on every node and here): connecting to one without it warns once per process.
Jobs read and write files by their paths, so on several machines those paths must be
on storage every node sees (e.g. the output folder on a shared file system).

At most ``workers`` jobs are in flight at once (the cluster's CPUs by default), each a
task of one CPU; the next starts as one finishes, and after a failure none does.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any, TypeVar

import ray
from ray._private import ray_constants
from ray.exceptions import AuthenticationError, GetTimeoutError, RayActorError, RayTaskError
from ray.util.queue import Queue

from twinrl_data.actors import CLOSE_S, ActorLost, check_arguments
from twinrl_data.errors import TwinrlError

Job = TypeVar("Job")
Result = TypeVar("Result")
Send = Callable[[Any], None]

LOOPBACK = "127.0.0.1"
POLL_S = 0.2  # how often the caller looks for finished jobs and messages

_warned_unauthenticated = False  # the warning about a cluster without tokens, once


def warn_unauthenticated() -> None:
    """Warn, once per process, that the cluster connected to runs without Ray's token
    authentication (this process would have needed ``RAY_AUTH_MODE=token`` otherwise)."""
    global _warned_unauthenticated
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "token" or _warned_unauthenticated:
        return
    _warned_unauthenticated = True
    warnings.warn(
        "this Ray cluster runs without token authentication: whoever reaches its ports "
        "can run code on its machines; start every node with RAY_AUTH_MODE=token and the "
        "same token (docs/guides/scale-out.md)",
        stacklevel=2,
    )


def _start_embedded(workers: int) -> None:
    """Ray on this machine for this process alone, on the loopback interface."""
    # ray.init moves a loopback node address to the machine's reachable one unless Ray
    # clusters are off (as on macOS and Windows); off, every Ray server binds 127.0.0.1.
    enabled = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(
            address="local",  # a new instance, whatever RAY_ADDRESS says
            num_cpus=workers,
            include_dashboard=False,  # no dashboard, so no job API to submit code through
            _node_ip_address=LOOPBACK,
            # Ray's notes at start-up (e.g. that it turned its token authentication on)
            # are not the command's output: the terminal shows what it shows without Ray.
            logging_level=logging.ERROR,
        )
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = enabled


def _connect(address: str) -> None:
    try:
        ray.init(address=address, logging_level=logging.WARNING)
    except AuthenticationError as err:
        raise TwinrlError(
            f"the Ray cluster at {address} refused this machine's token: set "
            "RAY_AUTH_MODE=token and the cluster's token (RAY_AUTH_TOKEN, or the file "
            f"~/.ray/auth_token) ({err.message})"
        ) from None
    except ConnectionError as err:
        raise TwinrlError(
            f"no Ray cluster at {address}: start one with Ray's `ray start` (a head, then "
            f"this machine joined to it) or name its head in `cluster` ({err})"
        ) from None
    warn_unauthenticated()


_started: set[str] = set()  # in a Ray worker: the initializers it ran


def _call(
    fn: Callable[..., Any],
    job: Any,
    messages: Queue | None,
    initializer: Callable[[], None] | None,
) -> Any:
    if initializer is not None:
        name = f"{initializer.__module__}.{initializer.__qualname__}"
        if name not in _started:
            initializer()
            _started.add(name)
    return fn(job) if messages is None else fn(job, messages.put)


_remote_call = ray.remote(num_cpus=1, max_retries=0)(_call)


class RayExecutor:
    """Jobs as Ray tasks, at most ``workers`` at a time (default: the cluster's CPUs);
    ``address`` is a cluster's, or ``None`` for Ray embedded here (see the module docstring);
    ``initializer`` runs once in each Ray worker process before its first job."""

    def __init__(
        self,
        workers: int | None,
        *,
        address: str | None = None,
        initializer: Callable[[], None] | None = None,
    ) -> None:
        if workers is not None and workers < 1:
            raise TwinrlError(f"an executor needs at least one worker, got {workers}")
        self._owns_ray = not ray.is_initialized()
        if self._owns_ray:
            if address is None:
                _start_embedded(workers or os.cpu_count() or 1)
            else:
                _connect(address)
        self.workers = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._initializer = initializer

    def map(self, fn: Callable[[Job], Result], jobs: Iterable[Job]) -> list[Result]:
        return self._gather(fn, list(jobs), None)

    def run(
        self,
        fn: Callable[[Job, Send], Result],
        jobs: Iterable[Job],
        on_message: Callable[[Any], None],
    ) -> list[Result]:
        return self._gather(fn, list(jobs), on_message)

    def _gather(
        self, fn: Callable[..., Any], jobs: list[Any], on_message: Callable[[Any], None] | None
    ) -> list[Any]:
        """Keep ``workers`` jobs in flight, passing messages on; none starts after a failure."""
        messages = None if on_message is None else Queue(actor_options={"num_cpus": 0})
        refs: list[Any] = []
        running: list[Any] = []
        failed = False
        try:
            while running or (len(refs) < len(jobs) and not failed):
                while not failed and len(refs) < len(jobs) and len(running) < self.workers:
                    ref = _remote_call.remote(fn, jobs[len(refs)], messages, self._initializer)
                    refs.append(ref)
                    running.append(ref)
                done, running = ray.wait(running, num_returns=1, timeout=POLL_S)
                failed = failed or any(_failed(ref) for ref in done)
                _deliver(messages, on_message)
            _deliver(messages, on_message)  # what the last jobs sent before they returned
            try:
                return ray.get(refs)
            except RayTaskError as err:  # the first failure, as the job raised it
                raise err.cause from err
        finally:
            if messages is not None:
                messages.shutdown()

    def actors(self, cls: type, inits: list[dict[str, Any]], *, gpus: float = 0) -> RayActors:
        """Actors of one CPU each, and ``gpus`` GPUs each (Ray shows an actor only the GPUs
        it reserved); refused when the cluster has fewer GPUs than one actor needs."""
        if gpus > self.gpus():
            raise TwinrlError(
                f"the cluster has fewer than {gpus:g} GPU(s) for an actor; add a node "
                "with a GPU to the cluster, or run it on the CPU (device cpu)"
            )
        return RayActors(cls, inits, gpus=gpus)

    def gpus(self) -> float:
        """The GPUs of the cluster, all nodes together."""
        return float(ray.cluster_resources().get("GPU", 0))

    def close(self) -> None:
        if self._owns_ray:
            ray.shutdown()

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RayActors:
    """Each object a Ray actor of one CPU and ``gpus`` GPUs (:mod:`twinrl_data.actors`),
    anywhere on the cluster that has them; an object's error is raised as it was raised,
    a gone actor as :class:`~twinrl_data.actors.ActorLost`."""

    def __init__(self, cls: type, inits: list[dict[str, Any]], *, gpus: float = 0) -> None:
        remote = ray.remote(num_cpus=1, num_gpus=gpus, max_restarts=0)(cls)
        self._handles = [remote.remote(**init) for init in inits]

    def call(self, method: str, args: Sequence[tuple], timeout_s: float | None = None) -> list[Any]:
        if not self._handles:
            raise ActorLost("these Ray actors were stopped; start new ones")
        check_arguments(len(self._handles), args)
        refs = [getattr(h, method).remote(*a) for h, a in zip(self._handles, args, strict=True)]
        try:
            return ray.get(refs, timeout=timeout_s)
        except RayTaskError as err:  # as the object raised it
            raise err.cause from err
        except RayActorError as err:  # it died, or its class could not make it
            raise ActorLost(f"a Ray actor of {method} stopped: {err}") from err
        except GetTimeoutError:  # out of step with its caller: of no more use
            self._kill()
            raise ActorLost(
                f"a Ray actor did not answer {method} within {timeout_s:g} s; it was stopped"
            ) from None

    def close(self) -> None:
        for handle in self._handles:
            try:
                if hasattr(handle, "close"):
                    ray.get(handle.close.remote(), timeout=CLOSE_S)
            except (RayTaskError, RayActorError, GetTimeoutError):
                pass
        self._kill()

    def _kill(self) -> None:
        for handle in self._handles:
            ray.kill(handle)
        self._handles = []


def _failed(ref: Any) -> bool:
    try:
        ray.get(ref)
    except RayTaskError:
        return True
    return False


def _deliver(messages: Queue | None, on_message: Callable[[Any], None] | None) -> None:
    if messages is None or on_message is None:
        return
    count = messages.qsize()
    if count:
        for message in messages.get_nowait_batch(count):
            on_message(message)
