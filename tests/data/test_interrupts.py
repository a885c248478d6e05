"""Ctrl-C reaches a command that began with SIGINT ignored (a script's background job)."""

import os
import signal
import threading

import pytest

from twinrl_data.interrupts import interruptible


def test_sigint_ignored_at_start_still_interrupts_the_block_and_is_ignored_again_after():
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as `twinrl record ... &` begins
    try:
        with pytest.raises(KeyboardInterrupt), interruptible():
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10_000_000):  # the handler runs between bytecodes
                pass
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def test_outside_the_main_thread_nothing_changes():
    seen = []

    def inside() -> None:
        with interruptible():
            seen.append(signal.getsignal(signal.SIGINT))

    thread = threading.Thread(target=inside)
    thread.start()
    thread.join()
    assert seen == [signal.getsignal(signal.SIGINT)]
