"""One writer per run folder: an exclusive `flock` on a lock file inside it, held while a
process writes the folder.

The kernel releases the lock when its holder exits, however it exits (a kill, a crash), so a
stale lock file never blocks a later run. The file holds the holder's pid for the message a
second process gets; it is written in place (it must stay the file that is locked), the one
file of a run folder not written through `atomic.py`, and only read for that message.

The lock never follows a link and never empties a file it did not make: a `.lock` that is a
symlink, a hard link, not a plain file or longer than a pid line is refused (a run folder
received from someone else cannot make a run truncate another file).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import stat
from pathlib import Path
from types import TracebackType

from pipeline.errors import UserError

LOCK_NAME = ".lock"
MAX_LOCK_BYTES = 32  # a pid line: anything longer is not a lock file this module wrote


class RunFolderBusy(UserError):
    """Another process is writing the run folder."""


class RunLock:
    """`with RunLock(folder):` holds the folder's lock, or raises RunFolderBusy naming the
    folder and the holder's pid. The folder must exist."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.path = folder / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> None:
        fd = self._open()
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            raise RunFolderBusy(
                f"{self.folder} is being written by another gsplatam process (pid {holder}): "
                "wait for it to end, or choose another --name"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def _open(self) -> int:
        """The lock file's descriptor: created, or an earlier lock file (never through a link)."""
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK
        if self.path.is_symlink():
            raise UserError(f"{self.path} is a symbolic link, not a lock file: remove it to use this run folder")
        try:
            fd = os.open(self.path, flags, 0o644)
        except OSError as exc:
            raise UserError(f"cannot lock the run folder {self.folder} ({self.path}): {exc.strerror}") from None
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1 or info.st_size > MAX_LOCK_BYTES:
            os.close(fd)
            raise UserError(
                f"{self.path} is not a lock file of gsplatam (a link, or not a plain file of a pid): "
                "remove it to use this run folder"
            )
        return fd

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            os.close(fd)  # closing the descriptor releases the lock

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.release()


def _read_pid(fd: int) -> str:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", errors="replace").strip()
    except OSError:
        text = ""
    return text or "unknown"
