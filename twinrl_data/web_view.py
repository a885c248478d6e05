"""Episodes in a browser: Rerun's web viewer served for a computer with no screen.

The computer beside a robot often has none. :func:`serve_web` writes the episodes'
recording (:func:`twinrl_data.view.save_rrd`) and runs the ``rerun`` program on it with
``--serve-web``: one server holds the recording (gRPC) and another hands browsers the
web viewer, both bound to ``bind`` only, loopback unless the user names an address.
(Rerun's Python ``serve_grpc``/``serve_web_viewer`` listen on every interface and take
no address, so they are not used.) The page's link carries the recording server's
address, so a browser on another machine connects to this one, not to itself.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from twinrl_data import schema as contract
from twinrl_data.errors import DataError
from twinrl_data.view import CellModel, save_rrd

LOOPBACK = "127.0.0.1"
START_TIMEOUT = 30.0  # s for the servers to listen


@dataclass
class WebViewer:
    """A running web viewer: its page's ``url``, the ``rerun`` process serving it."""

    url: str
    process: subprocess.Popen
    recording: Path

    def wait(self) -> int:
        """Serve until the process ends (Ctrl-C); returns its exit status."""
        try:
            return self.process.wait()
        finally:
            self.close()

    def close(self) -> None:
        """Stop serving and remove the recording written for it."""
        # The whole process group: ``python -m rerun`` runs the viewer as a child of its own.
        if self.process.poll() is None or _group_alive(self.process.pid):
            _signal_group(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                _signal_group(self.process.pid, signal.SIGKILL)
            deadline = time.monotonic() + 10
            while _group_alive(self.process.pid) and time.monotonic() < deadline:
                time.sleep(0.1)
        shutil.rmtree(self.recording.parent, ignore_errors=True)


def serve_web(
    episodes: Sequence[contract.Episode],
    *,
    cell: CellModel | None = None,
    bind: str = LOOPBACK,
    web_port: int = 9090,
    grpc_port: int = 9876,
) -> WebViewer:
    """Serve ``episodes`` (as :func:`~twinrl_data.view.save_rrd` logs them) to browsers
    on ``bind``; returns once both servers listen."""
    for port, name in ((web_port, "web_port"), (grpc_port, "grpc_port")):
        if _taken(bind, port):
            raise DataError(
                f"port {port} on {bind} is in use; choose another `{name}` or stop what "
                "listens there"
            )
    folder = Path(tempfile.mkdtemp(prefix="twinrl-web-"))
    recording = save_rrd(episodes, folder / "episodes.rrd", cell=cell)
    command = [
        sys.executable, "-m", "rerun", "--serve-web", "--bind", bind, "--port", str(grpc_port),
        "--web-viewer-port", str(web_port), str(recording),
    ]  # fmt: skip
    process = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    # Every interface: the page names this machine as others on the network reach it.
    host = socket.gethostname() if bind in ("0.0.0.0", "::") else bind
    viewer = WebViewer(
        url=f"http://{host}:{web_port}/?url={quote(f'rerun+http://{host}:{grpc_port}/proxy')}",
        process=process,
        recording=recording,
    )
    deadline = time.monotonic() + START_TIMEOUT
    while not (_taken(bind, web_port) and _taken(bind, grpc_port)):
        if process.poll() is not None or time.monotonic() > deadline:
            viewer.close()
            raise DataError(
                f"rerun's web viewer did not start on {bind} (ports {web_port}, {grpc_port}); "
                "check that the address is this machine's"
            )
        time.sleep(0.1)
    return viewer


def _signal_group(pid: int, number: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(pid, number)


def _group_alive(pid: int) -> bool:
    try:
        os.killpg(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _taken(host: str, port: int) -> bool:
    """Whether something listens on ``host``:``port``."""
    target = LOOPBACK if host in ("0.0.0.0", "::") else host
    with socket.socket(socket.AF_INET6 if ":" in target else socket.AF_INET) as probe:
        probe.settimeout(0.5)
        return probe.connect_ex((target, port)) == 0
