"""Episodes in a browser: Rerun's web viewer served for a computer with no screen.

The computer beside a robot often has none. :func:`start_web_viewer` runs rerun's own
program with ``--serve-web``: a server that holds what is logged to it (gRPC) and one
that hands browsers the web viewer, both bound to ``bind`` only, loopback unless the user
names an address. (Rerun's Python ``serve_grpc``/``serve_web_viewer`` listen on every
interface and take no address, so they are not used.) A recording stream logs to it at
:attr:`WebViewer.grpc_url`: :func:`serve_web` sends saved episodes, a recording session's
live view its steps as they come. The page's link carries the recording server's
address, so a browser on another machine connects to this one, not to itself.

The episodes are streamed to the server rather than named to it as a file: rerun 0.33
serving a file spins a core for as long as it serves. The server dies with the thread
that started it (Linux's parent-death signal) however that ends, and
:meth:`WebViewer.wait` stops it on SIGINT (Ctrl-C) or SIGTERM even where the process
began with SIGINT ignored, as a script's background job does.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from urllib.parse import quote

import rerun as rr

from twinrl_data import schema as contract
from twinrl_data.errors import DataError
from twinrl_data.interrupts import interruptible
from twinrl_data.view import CellModel, log_episodes

LOOPBACK = "127.0.0.1"
START_TIMEOUT = 30.0  # s for the servers to listen
STOP_TIMEOUT = 10.0  # s for the server to end on SIGTERM before it is killed
_PR_SET_PDEATHSIG = 1  # prctl(2)


@dataclass
class WebViewer:
    """A running web viewer: its page's ``url``, the ``grpc_url`` a recording stream logs
    to, the rerun ``process`` serving both."""

    url: str
    grpc_url: str
    process: subprocess.Popen

    def __enter__(self) -> WebViewer:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close()

    def wait(self) -> None:
        """Serve until the server ends or this process gets SIGINT (Ctrl-C) or SIGTERM,
        then stop it; call from the main thread."""
        try:
            with interruptible(signal.SIGINT, signal.SIGTERM):
                self.process.wait()
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        """Stop serving: SIGTERM to the server's process group, SIGKILL if it lingers."""
        if self.process.poll() is not None:
            return
        _signal_group(self.process.pid, signal.SIGTERM)
        try:
            self.process.wait(timeout=STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            _signal_group(self.process.pid, signal.SIGKILL)
            self.process.wait()


def start_web_viewer(
    *, bind: str = LOOPBACK, web_port: int = 9090, grpc_port: int = 9876
) -> WebViewer:
    """Start rerun's web viewer and recording server on ``bind``; returns once both
    listen. Stop it with :meth:`WebViewer.close` (or use it as a context manager)."""
    for port, name in ((web_port, "web_port"), (grpc_port, "grpc_port")):
        if _taken(bind, port):
            raise DataError(
                f"port {port} on {bind} is in use; choose another `{name}` or stop what "
                "listens there"
            )
    command = [
        _rerun_program(), "--serve-web", "--bind", bind, "--port", str(grpc_port),
        "--web-viewer-port", str(web_port),
    ]  # fmt: skip
    process = subprocess.Popen(
        command,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=die_with_parent(),
    )
    # Every interface: the page names this machine as others on the network reach it.
    every = bind in ("0.0.0.0", "::")
    host = _url_host(socket.gethostname() if every else bind)
    grpc_url = f"rerun+http://{host}:{grpc_port}/proxy"
    viewer = WebViewer(
        url=f"http://{host}:{web_port}/?url={quote(grpc_url)}",
        grpc_url=f"rerun+http://{_url_host(LOOPBACK if every else bind)}:{grpc_port}/proxy",
        process=process,
    )
    with _closed_on_error(viewer):
        deadline = time.monotonic() + START_TIMEOUT
        while not (_taken(bind, web_port) and _taken(bind, grpc_port)):
            if process.poll() is not None or time.monotonic() > deadline:
                raise DataError(
                    f"rerun's web viewer did not start on {bind} (ports {web_port}, "
                    f"{grpc_port}); check that the address is this machine's"
                )
            time.sleep(0.1)
    return viewer


def serve_web(
    episodes: Sequence[contract.Episode],
    *,
    cell: CellModel | None = None,
    bind: str = LOOPBACK,
    web_port: int = 9090,
    grpc_port: int = 9876,
) -> WebViewer:
    """Serve ``episodes`` (logged as :func:`~twinrl_data.view.save_rrd` logs them) to
    browsers on ``bind``; returns once the server holds them."""
    viewer = start_web_viewer(bind=bind, web_port=web_port, grpc_port=grpc_port)
    with _closed_on_error(viewer):
        recording = rr.RecordingStream("twinrl", recording_id=episodes[0].meta.episode_id)
        recording.connect_grpc(viewer.grpc_url)
        log_episodes(episodes, recording, cell=cell)
        recording.flush()
        recording.disconnect()
    return viewer


@contextlib.contextmanager
def _closed_on_error(viewer: WebViewer) -> Iterator[None]:
    """Stop ``viewer`` when the block raises anything, Ctrl-C included."""
    try:
        yield
    except BaseException:
        viewer.close()
        raise


def _rerun_program() -> str:
    """The ``rerun`` program that rerun-sdk ships (``python -m rerun`` runs it as a child
    of a Python process of its own, one more process to stop)."""
    import rerun_cli

    program = Path(rerun_cli.__file__).with_name("rerun")
    if not program.is_file():
        raise DataError(f"rerun's program is missing from {program.parent}; reinstall rerun-sdk")
    return str(program)


def die_with_parent() -> Callable[[], None] | None:
    """What a child process runs before its program (`preexec_fn`): ask Linux for SIGTERM
    when its parent dies (rerun's server, the live view's writer)."""
    if not sys.platform.startswith("linux"):
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up before the fork

    def arm() -> None:
        prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM))

    return arm


def _signal_group(pid: int, number: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(pid, number)


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _taken(host: str, port: int) -> bool:
    """Whether something listens on ``host``:``port``."""
    target = LOOPBACK if host in ("0.0.0.0", "::") else host
    with socket.socket(socket.AF_INET6 if ":" in target else socket.AF_INET) as probe:
        probe.settimeout(0.5)
        return probe.connect_ex((target, port)) == 0
