"""`--web` in a real headless browser: the page of `twinrl view --web` loads, connects to
the recording server and receives the episode; that of `twinrl record --web` follows a
recording session as it is recorded. Every process a test starts is stopped after it."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest

from tests.data.test_web_view import free_ports, wait_until
from tests.web_browser import Traffic, chromium, needs_chromium
from twinrl_data.repair import verify
from twinrl_data.session import Session

TWINRL = [sys.executable, "-m", "twinrl_learn"]
pytestmark = needs_chromium()


@contextlib.contextmanager
def _running(command: list[str], cwd: Path) -> Iterator[subprocess.Popen]:
    """``command`` running; Ctrl-C'd on leaving. One that does not stop within 60 s is
    aborted, so that it prints every thread's stack (faulthandler), killed with its
    children, and the test fails with where it hung."""
    process = subprocess.Popen(
        command, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env=os.environ | {"PYTHONFAULTHANDLER": "1"},
    )  # fmt: skip
    try:
        yield process
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            children = psutil.Process(process.pid).children(recursive=True)
            process.send_signal(signal.SIGABRT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(timeout=10)
            for child in [*children, process]:
                with contextlib.suppress(psutil.NoSuchProcess):
                    child.kill()
            stacks = process.stderr.read()[-6000:]
            hung = f"still running 60 s after Ctrl-C; its threads:\n{stacks}"
            raise AssertionError(hung) from None


def _page(process: subprocess.Popen, says: str) -> str:
    """The web viewer's page from the line of ``process``'s output that offers it."""
    for line in process.stdout:
        if says in line:
            return line.split("open ")[1].split()[0]
    raise AssertionError(f"no '{says}' line: {process.stderr.read()}")


def test_the_page_loads_connects_and_receives_the_episode(tmp_path: Path) -> None:
    from twinrl_robot.scripted import run_scripted_expert

    session = Session.create(tmp_path / "session")
    run_scripted_expert("pick_place", world="twin", episodes=1, session=session, seed=3)
    saved = subprocess.run([*TWINRL, "view", "session#0", "--save", "episode.rrd"],
                           cwd=tmp_path, capture_output=True, timeout=120)  # fmt: skip
    assert saved.returncode == 0, saved.stderr
    size = (tmp_path / "episode.rrd").stat().st_size
    web, grpc = free_ports()
    command = [*TWINRL, "view", "session#0", "--web", "--web-port", str(web),
               "--grpc-port", str(grpc)]  # fmt: skip
    with _running(command, tmp_path) as server, chromium() as browser:
        browser.get(_page(server, "open http://127.0.0.1:"))
        assert browser.title == "Rerun Viewer"
        traffic = Traffic(grpc)

        def received() -> bool:
            traffic.read(browser)
            return traffic.received > 0.8 * size

        got = wait_until(received, 90, poll=0.5)
        assert any("ReadMessages" in url for url in traffic.requests.values()), traffic
        # The whole episode, as the recording's own file holds it, reached the page.
        assert got, f"the page received {traffic.received} of the episode's {size} bytes"
        canvas = browser.execute_script(
            "const c = document.querySelector('canvas'); return c && [c.width, c.height]"
        )
        assert canvas and min(canvas) > 100


@pytest.mark.slow  # about 30 s
@pytest.mark.realtime  # the scripted person drives at the control rate
def test_the_page_follows_a_recording_session_live(tmp_path: Path) -> None:
    # More episodes than the test waits for: on a loaded host the browser took longer to
    # start than three episodes take to record. Once the page is seen following, the
    # browser closes and then the session is stopped with Ctrl-C, which keeps every
    # episode recorded so far. (With rerun's calls in the recorder's process, a recorder
    # stopped after its page had closed once hung inside rerun's log call; they run in
    # the live view's own process now.)
    web, grpc = free_ports()
    command = [*TWINRL, "record", "--out", "session", "--teleop", "scripted", "--no-keys",
               "--episodes", "30", "--web", "--web-port", str(web),
               "--grpc-port", str(grpc)]  # fmt: skip
    with _running(command, tmp_path) as recorder, chromium() as browser:
        browser.get(_page(recorder, "live view: open http://127.0.0.1:"))
        traffic = Traffic(grpc)
        seen: list[int] = []  # bytes received so far, while the session records

        def growing() -> bool:  # more arrives as the episodes are recorded
            traffic.read(browser)
            if recorder.poll() is not None:
                return True
            if traffic.received:
                seen.append(traffic.received)
            return len(seen) > 1 and seen[-1] > seen[0] + 100_000

        assert wait_until(growing, 120, poll=0.5)
        assert recorder.poll() is None, "the session ended before the page was seen following"
        assert len(seen) > 1 and seen[-1] > seen[0] + 100_000, ("not seen growing", seen)
    assert recorder.returncode == 130, recorder.stderr.read()  # stopped by Ctrl-C
    assert "stopped (Ctrl-C): session holds" in recorder.stdout.read()
    assert Session(tmp_path / "session").episode_paths()
    assert not verify(tmp_path / "session").problems
