"""Writing so that a crash, a kill or a full disk never leaves half a file or folder.

- :func:`write_atomic`: a small file (a manifest, a report) is written beside its path,
  fsynced, renamed over it and its folder fsynced: the path holds the old or the new
  content, never a mix. Permissions come from the umask, as for any new file.
- :func:`publishing`: a derived folder (a dataset, a checkpoint) is built beside its
  path and renamed into place at the end, so the path holds a complete result or
  nothing; what an interrupted build left behind is cleared by the next one.
- :func:`require_free_space`: refuse to start writing without a margin free.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

from twinrl_data.errors import DataError

PARTIAL = ".partial-"  # infix of a folder being built: <name>.partial-<host>-<pid>


def fsync_folder(folder: Path) -> None:
    """Make a rename or a new file in ``folder`` durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` in one step (see the module docstring)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(temporary, path)
    except OSError as err:
        temporary.unlink(missing_ok=True)
        raise disk_error(err, path) from None
    fsync_folder(path.parent)


def disk_error(err: OSError, path: Path) -> DataError:
    """A write that failed, as one line that says what to do."""
    if err.errno == errno.ENOSPC:
        return DataError(f"the disk holding {path} is full; free some space and run again")
    if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return DataError(
            f"{path} cannot be written ({err.strerror}); check the folder's permissions"
        )
    return DataError(f"writing {path} failed ({err.strerror or err}); check the disk and run again")


def require_free_space(folder: str | Path, needed: int, what: str) -> None:
    """Refuse to start ``what`` unless ``needed`` bytes are free where ``folder`` lives."""
    folder = Path(folder)
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    free = shutil.disk_usage(existing).free
    if free < needed:
        raise DataError(
            f"only {free / 2**20:.0f} MiB are free on the disk holding {folder}; {what} needs "
            f"at least {needed / 2**20:.0f} MiB: free some space or write elsewhere"
        )


def owner_tag() -> str:
    """This process, as ``<host>-<pid>``: who is writing something."""
    return f"{socket.gethostname()}-{os.getpid()}"


def owner_alive(tag: str) -> bool:
    """Whether the process ``tag`` (see :func:`owner_tag`) may still run: it does on
    this host, or it is another host's (which cannot be asked)."""
    host, _, pid = tag.rpartition("-")
    if host != socket.gethostname() or not pid.isdigit():
        return True
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def publishing(final: str | Path) -> Iterator[Path]:
    """Build a folder beside ``final`` and rename it into place when the block ends.

    Yields the folder to build in (not yet created: the builder makes it, as libraries
    that refuse an existing folder want). On an exception it is removed and ``final`` is left
    as it was; folders that killed builds of ``final`` left on this host are cleared
    first. ``final`` must not exist when the block ends (the caller decides beforehand
    whether to replace an old one).
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    for leftover in final.parent.glob(f"{final.name}{PARTIAL}*"):
        if not owner_alive(leftover.name.rpartition(PARTIAL)[2]):
            shutil.rmtree(leftover, ignore_errors=True)
    building = final.with_name(f"{final.name}{PARTIAL}{owner_tag()}")
    shutil.rmtree(building, ignore_errors=True)
    try:
        yield building
        if not building.exists():
            raise DataError(f"nothing was written for {final}")
        if final.exists():
            raise DataError(f"{final} appeared while it was being built; choose another path")
        os.replace(building, final)
        fsync_folder(final.parent)
    except BaseException:
        shutil.rmtree(building, ignore_errors=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """:func:`write_atomic` for text (reports, JSON results, scene specs)."""
    write_atomic(path, text.encode())
