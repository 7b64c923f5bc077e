"""Every file a run writes goes through here: a temporary file beside the target, flushed and
fsynced, then renamed over it. A kill or a full disk leaves the old file or the new one, never
half of one, and no temporary file behind.

`atomic_write_all` does this for a set of files that belong together (trajectory, map and
checkpoint of one moment): every temporary file is written first and only then are they renamed,
so a write that fails (a full disk) replaces none of them and the last complete set stays.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO

Writer = Callable[[IO[bytes]], None]


def atomic_write(path: Path, write: Writer) -> None:
    """Call `write(file)` on a temporary file in `path`'s folder, then replace `path` with it."""
    atomic_write_all({path: write})


def atomic_write_all(writes: Mapping[Path, Writer]) -> None:
    """Write every file of `writes` to a temporary file, then replace the targets one by one.
    If any write fails, no target is replaced and every temporary file is removed."""
    staged: list[tuple[str, Path]] = []
    try:
        for path, write in writes.items():
            staged.append((_write_temporary(path, write), path))
        for tmp, path in staged:
            os.replace(tmp, path)
    except BaseException:
        for tmp, _ in staged:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        raise
    for folder in {path.parent for path in writes}:
        _sync_folder(folder)


def _write_temporary(path: Path, write: Writer) -> str:
    """-> the name of a fsynced temporary file beside `path` holding what `write` wrote."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return tmp


def atomic_export(path: Path, export: Callable[[Path], None]) -> None:
    """For a library that writes a file itself, by name (the torch profiler's trace): `export`
    writes a temporary path beside `path`, which is renamed over `path` once complete."""
    staged = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        export(staged)
        os.replace(staged, path)
    except BaseException:
        with contextlib.suppress(OSError):
            staged.unlink()
        raise
    _sync_folder(path.parent)


def bytes_writer(data: bytes) -> Writer:
    def write(f: IO[bytes]) -> None:
        f.write(data)

    return write


def atomic_write_bytes(path: Path, data: bytes) -> None:
    atomic_write(path, bytes_writer(data))


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def _sync_folder(folder: Path) -> None:
    """Make the rename itself durable (where the platform allows opening a folder)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
