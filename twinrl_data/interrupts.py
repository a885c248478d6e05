"""Ctrl-C that stops a command even where it began with SIGINT ignored.

A job a script starts in the background (``twinrl record ... &``) inherits SIGINT
ignored, and Python then raises no ``KeyboardInterrupt`` for it: a ``kill -INT`` (or a
test's) would leave a recording or a server running. :func:`interruptible` turns the
given signals into ``KeyboardInterrupt`` for the time of a ``with`` block in the main
thread, and puts the handlers back after it.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def interruptible(*numbers: signal.Signals) -> Iterator[None]:
    """Within the block, each of ``numbers`` (default: SIGINT) raises
    ``KeyboardInterrupt`` in the main thread; elsewhere than the main thread, nothing
    changes (only it may set handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous: dict[signal.Signals, Any] = {}
    try:
        for number in numbers or (signal.SIGINT,):
            previous[number] = signal.signal(number, signal.default_int_handler)
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
