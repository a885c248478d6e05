"""Rerun's web viewer served from this machine stops however twinrl is stopped: Ctrl-C
even when twinrl began with SIGINT ignored (a script's background job), and the death of
the process that started it. Every test stops what it started, also when it fails."""

import contextlib
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import psutil
import pytest

from twinrl_data.errors import DataError
from twinrl_data.web_view import start_web_viewer


def free_ports(count: int = 2) -> list[int]:
    """``count`` different ports free on loopback (held together while picked)."""
    with contextlib.ExitStack() as stack:
        probes = [stack.enter_context(socket.socket()) for _ in range(count)]
        for probe in probes:
            probe.bind(("127.0.0.1", 0))
        return [probe.getsockname()[1] for probe in probes]


def _listens(port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(1)
        return probe.connect_ex(("127.0.0.1", port)) == 0


def wait_until(condition, timeout: float, poll: float = 0.05) -> bool:
    """Whether ``condition()`` holds within ``timeout`` s, asked every ``poll`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll)
    return True


def test_wait_stops_the_server_on_sigint_even_if_started_ignoring_it():
    web, grpc = free_ports()
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a script's `twinrl ... &`
    viewer = start_web_viewer(web_port=web, grpc_port=grpc)
    try:
        assert _listens(web) and _listens(grpc)
        sent: list[float] = []

        def press_ctrl_c() -> None:  # once wait() handles it; else the guard below ends it
            handled = lambda: signal.getsignal(signal.SIGTERM) is signal.default_int_handler  # noqa: E731
            if wait_until(handled, 20):
                sent.append(time.monotonic())
                os.kill(os.getpid(), signal.SIGINT)
            if not wait_until(lambda: viewer.process.poll() is not None, 20):
                viewer.process.kill()

        threading.Thread(target=press_ctrl_c, daemon=True).start()
        viewer.wait()
        stopped = time.monotonic()
        assert sent and stopped - sent[0] < 10, "Ctrl-C did not stop serving"
        assert viewer.process.returncode == -signal.SIGTERM  # stopped, not killed
        assert not _listens(web) and not _listens(grpc)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # as it was
    finally:
        signal.signal(signal.SIGINT, before)
        viewer.close()


def test_the_server_dies_with_the_process_that_started_it():
    web, grpc = free_ports()
    script = textwrap.dedent(f"""
        import time
        from twinrl_data.web_view import start_web_viewer
        viewer = start_web_viewer(web_port={web}, grpc_port={grpc})
        print(viewer.process.pid, flush=True)
        time.sleep(60)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    server = None
    try:
        server = psutil.Process(int(parent.stdout.readline()))
        assert wait_until(lambda: _listens(web) and _listens(grpc), 30)
        family = {server.pid, *(c.pid for c in server.children(recursive=True))}
        parent.kill()  # no chance to clean up
        parent.wait(timeout=10)
        assert wait_until(lambda: not server.is_running() or server.status() == "zombie", 10)
        # Nothing of the server's serves on: a port freed here may already be another
        # test's (the parallel suite binds many), so the listeners are asked who they are.
        listeners = {
            c.pid
            for c in psutil.net_connections("inet")
            if c.status == psutil.CONN_LISTEN and c.laddr.port in (web, grpc)
        }
        assert not listeners & family
    finally:
        parent.kill()
        if server is not None and server.is_running():
            server.kill()


def test_a_port_in_use_is_one_clear_error():
    web, grpc = free_ports()
    with (
        start_web_viewer(web_port=web, grpc_port=grpc) as viewer,
        pytest.raises(DataError, match=f"port {web} on 127.0.0.1 is in use"),
    ):
        start_web_viewer(web_port=web, grpc_port=free_ports(1)[0])
    assert viewer.process.poll() is not None and not _listens(web)
