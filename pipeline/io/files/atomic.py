"""Every file a run writes goes through here: a temporary file beside the target, flushed and
fsynced, then renamed over it. A kill or a full disk leaves the old file or the new one, never
half of one, and no temporary file behind. Files get the mode the umask leaves of 0666 (0644
under the usual 022) and folders that of 0777, as `open` and `mkdir` give them: a temporary file
alone would be 0600, unreadable to a web server, another user or a container of another uid.

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
TEMPORARY_PREFIX = (
    ".gsplatam-"  # every temporary name this tool makes starts so: a user's `.notes.tmp` is never taken for one
)
FILE_MODE = 0o666  # less the umask, as open() creates files
FOLDER_MODE = 0o777  # less the umask, as mkdir() creates folders


def current_umask() -> int:
    """The process's umask, read without changing it where Linux says it (/proc), else set and
    restored at once (another thread creating a file in between would get mode 0666/0777)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def temporary_name(path: Path, tag: str) -> Path:
    """A temporary name beside `path` (`tag` makes it unique), with this tool's prefix."""
    return path.with_name(f"{TEMPORARY_PREFIX}{path.name}.{tag}.tmp")


def temporaries_of(pattern: str) -> tuple[str, ...]:
    """Glob patterns, relative as `pattern` is, of the temporary files and folders this tool
    leaves beside a file matching `pattern` when killed while writing it: with its prefix, and
    as versions before the prefix named them (`.NAME.*.tmp`)."""
    folder, _, name = pattern.rpartition("/")
    beside = f"{folder}/" if folder else ""
    return f"{beside}{TEMPORARY_PREFIX}{name}.*.tmp", f"{beside}.{name}.*.tmp"


def temporary_folder(parent: Path, name: str) -> Path:
    """A new empty folder in `parent` for a set of files that is renamed into place once whole
    as `name`, with the mode a plain mkdir gives (mkdtemp's own is 0700)."""
    path = Path(tempfile.mkdtemp(prefix=f"{TEMPORARY_PREFIX}{name}.", suffix=".tmp", dir=parent))
    path.chmod(FOLDER_MODE & ~current_umask())
    return path


def atomic_write(path: Path, write: Writer) -> None:
    """Call `write(file)` on a temporary file in `path`'s folder, then replace `path` with it."""
    atomic_write_all({path: write})


def atomic_write_all(writes: Mapping[Path, Writer]) -> None:
    """Write every file of `writes` to a temporary file, then replace the targets one by one, in
    the order of `writes`. If any write fails, no target is replaced and every temporary file is
    removed; a process killed between two replacements leaves the earlier targets new."""
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


def _new_temporary(path: Path) -> tuple[int, str]:
    """A new file beside `path`, created exclusively under a random name (never through a link),
    with the mode the umask leaves of FILE_MODE: (its descriptor, its name)."""
    fd, name = tempfile.mkstemp(prefix=f"{TEMPORARY_PREFIX}{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, FILE_MODE & ~current_umask())
    except BaseException:
        os.close(fd)
        os.unlink(name)
        raise
    return fd, name


def _write_temporary(path: Path, write: Writer) -> str:
    """-> the name of a fsynced temporary file beside `path` holding what `write` wrote."""
    fd, tmp = _new_temporary(path)
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
    writes a temporary path beside `path`, which is renamed over `path` once complete. The
    temporary file is created first, exclusively and under a random name (`mkstemp`), so the
    library writes into a plain file of ours, never through a link planted at a guessable name."""
    fd, name = _new_temporary(path)
    os.close(fd)
    staged = Path(name)
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
