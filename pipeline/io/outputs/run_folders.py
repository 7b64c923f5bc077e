"""Claiming the folder a run writes: its name, its lock and `latest`, in one place. A fresh folder
per run, never an earlier run's, and one writer at a time.

Without a name a run gets `<stem>-YYYYmmdd-HHMMSS` under the output folder (`-2`, `-3`, ...
when two start in one second). Every new run folder carries the run marker (`RunFolder.mark`).
A named folder that holds an earlier run's results is refused unless `overwrite`, which first
removes that run's files (and only those), and only in a run folder of this tool: one with the
marker or, from before the marker, with both config.toml and frames.csv (a dataset holding a
`groundtruth.txt` is never touched). `--resume` is the one way to continue a run folder.

When a new run ends having saved something, the output folder's `latest` points at it (a
symlink, or a text file naming it where the file system has no symlinks); a run that processed
no frame (it failed or was stopped before its first) removes what it wrote, its folder with it
when nothing else is left there, and leaves `latest` alone. A folder holding a processed frame
is never removed. A `latest` that is not this
module's pointer (a user's own file, folder or link to elsewhere) is never replaced: the run
says so in one line and goes on.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.files.atomic import atomic_write_text, temporary_name
from pipeline.io.files.folders import make_folder
from pipeline.io.outputs.run_folder import MARKER, RunFolder

log = logging.getLogger("gsplatam")

LATEST = "latest"
MAX_POINTER_BYTES = 256  # a `latest` text file longer than this names no run folder


def check_output(output: Path) -> None:
    """Make sure run folders can be made under `output` (created if missing), or say why not."""
    make_folder(output, "the output folder")
    if not os.access(output, os.W_OK | os.X_OK):
        raise UserError(f"cannot write into the output folder {output}: permission denied")


@contextlib.contextmanager
def new_run_folder(output: Path, stem: str, name: str = "", overwrite: bool = False) -> Iterator[RunFolder]:
    """A folder for a new run under `output`, locked while the caller writes it: `name` if given
    (refused while it holds an earlier run, unless `overwrite`), else `<stem>-<timestamp>`."""
    check_output(output)
    if name == LATEST:
        raise UserError(f"'{LATEST}' names the pointer to the newest run: choose another --name")
    if name:
        _refuse_earlier_run(RunFolder(output / name), overwrite)  # before the lock file: a refusal writes nothing
    folder = RunFolder(_named(output, name) if name else _timestamped(output, stem))
    with folder.claimed():
        if name:
            _clear_earlier_run(folder, overwrite)
        folder.mark()
        try:
            yield folder
        finally:
            _settle(folder)


@contextlib.contextmanager
def resumed_run_folder(folder: RunFolder) -> Iterator[RunFolder]:
    """An earlier run's folder (to continue it), locked while the caller writes it."""
    if not folder.path.is_dir():
        raise UserError(f"no run folder at {folder.path}")
    with folder.claimed():
        yield folder


def _named(output: Path, name: str) -> Path:
    return make_folder(output / name, "the run folder")


def _timestamped(output: Path, stem: str) -> Path:
    base = f"{stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    for attempt in range(1, 1000):
        folder = output / (base if attempt == 1 else f"{base}-{attempt}")
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            raise UserError(f"cannot create the run folder {folder}: {exc.strerror}") from None
        return folder
    raise UserError(f"cannot find a free run folder name for {output / base}")


def _clear_earlier_run(folder: RunFolder, overwrite: bool) -> None:
    """Remove the earlier run in `folder` (locked), if there is one and `overwrite` allows it."""
    if _refuse_earlier_run(folder, overwrite):
        folder.remove_earlier_run()
        log.info("--overwrite: removed the earlier run's files from %s", folder.path)


def _refuse_earlier_run(folder: RunFolder, overwrite: bool) -> bool:
    """UserError where `folder` holds files of a run that a new run may not replace; -> whether
    it holds any (to be removed, with `overwrite`)."""
    found = folder.earlier_run() if folder.path.is_dir() else []
    if not found:
        return False
    if not folder.is_run():
        raise UserError(
            f"{folder.path} holds {', '.join(found)} but is not a run folder of gsplatam (no {MARKER}, nor "
            "config.toml with frames.csv): a run never writes there, even with --overwrite; choose another --name"
        )
    if not overwrite:
        raise UserError(
            f"{folder.path} holds an earlier run ({', '.join(found)}): continue it with "
            f"--resume {folder.path}, replace it with --overwrite, or choose another --name"
        )
    return True


def _settle(folder: RunFolder) -> None:
    """After a new run: `latest` names it if it saved anything, else what it wrote goes."""
    try:
        if folder.holds_results():
            _point_latest_at(folder.path)
            return
        if folder.frame_timestamps():  # a folder holding a processed frame is never removed
            log.info("%s is kept: frames.csv holds frames processed, though no map was saved", folder.path)
            return
        folder.remove_unfinished()
        log.info("nothing was saved: removed what this run wrote in %s", folder.path)
    except OSError as exc:
        log.warning("could not tidy up %s: %s", folder.path, exc.strerror or exc)


def _is_pointer(latest: Path) -> bool:
    """Whether `latest` is absent or this module's pointer: a symlink to a name beside it, or a
    one-line text file naming a run folder beside it."""
    if latest.is_symlink():
        return "/" not in os.readlink(latest)
    if not latest.exists():
        return True
    if not latest.is_file() or latest.stat().st_size > MAX_POINTER_BYTES:
        return False
    name = latest.read_text(errors="replace").strip()
    return bool(name) and "/" not in name and "\n" not in name and RunFolder(latest.parent / name).is_run()


def _point_latest_at(folder: Path) -> None:
    """`latest` beside `folder` names it: a relative symlink replaced atomically, or a text file.
    A `latest` of the user's is left as it is."""
    latest = folder.parent / LATEST
    if not _is_pointer(latest):
        log.warning("%s is not gsplatam's pointer to the newest run (a file or folder of yours): left as it is", latest)
        return
    staged = temporary_name(folder.parent / LATEST, str(os.getpid()))
    try:
        with contextlib.suppress(FileNotFoundError):
            staged.unlink()
        try:
            os.symlink(folder.name, staged, target_is_directory=True)
        except OSError:  # no symlinks on this file system
            atomic_write_text(latest, folder.name + "\n")
            return
        os.replace(staged, latest)
    except OSError as exc:
        with contextlib.suppress(OSError):
            staged.unlink()
        log.warning("could not point %s at %s: %s", latest, folder.name, exc.strerror)
