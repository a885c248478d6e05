"""An exclusive lock on a folder, held by one process at a time.

``fcntl.flock`` on ``<folder>/.lock``: the kernel releases the lock when its holder
exits or is killed, so a crash never leaves a session locked; the file keeps the last
holder's process, host and start time, which a waiting process names when it gives up.
Locks are meant for local disks (network file systems may not honour them).
"""

from __future__ import annotations

import datetime as dt
import errno
import fcntl
import json
import os
import socket
import time
from pathlib import Path
from types import TracebackType

from twinrl_data.errors import DataError

LOCK_FILE = ".lock"
WAIT_SECONDS = 30.0  # a writer holds the lock for a manifest update: milliseconds
POLL_SECONDS = 0.02


class FolderLock:
    """``with FolderLock(folder):`` holds ``folder``'s lock for the block.

    Raises :class:`~twinrl_data.errors.DataError` naming the holder when the lock stays
    taken for ``wait`` seconds. ``file`` names the lock file in ``folder`` (one folder
    may hold locks on several things) and ``what`` the thing locked, in the error. A lock
    held for an object's lifetime rather than a block: :meth:`acquire`, :meth:`release`.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        wait: float = WAIT_SECONDS,
        file: str = LOCK_FILE,
        what: str | None = None,
    ) -> None:
        self.folder = Path(folder)
        self.path = self.folder / file
        self.wait = wait
        self.what = what or str(self.folder)
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        """Take the lock (see the class docstring); returns the lock."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as err:
            raise DataError(
                f"cannot lock {self.folder} ({err.strerror}); check that the folder exists "
                "and can be written"
            ) from None
        deadline = time.monotonic() + self.wait
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as err:
                if err.errno not in (errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                if time.monotonic() >= deadline:
                    holder = _holder(fd)
                    os.close(fd)
                    raise DataError(
                        f"{self.what} is locked by {holder}; wait for it to finish or stop "
                        "that process"
                    ) from None
                time.sleep(POLL_SECONDS)
        self._fd = fd
        record = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        return self

    def release(self) -> None:
        """Let the lock go (nothing when it is not held)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.release()


def _holder(fd: int) -> str:
    """The process named in the lock file, in words."""
    try:
        record = json.loads(os.pread(fd, 4096, 0) or b"{}")
        return f"process {record['pid']} on {record['host']} since {record['since']}"
    except (ValueError, KeyError, OSError):
        return "another process"
