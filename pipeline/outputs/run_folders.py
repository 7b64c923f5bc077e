"""Claiming the folder a run writes: its name, its lock and `latest`, in one place. A fresh folder
per run, never an earlier run's, and one writer at a time.

Without a name a run gets `<stem>-YYYYmmdd-HHMMSS` under the output folder (`-2`, `-3`, ...
when two start in one second) and the output folder's `latest` points at the newest run (a
symlink, or a text file naming it where the file system has no symlinks). A named folder that
holds an earlier run's results is refused unless `overwrite`, which first removes that run's
files (and only those). `--resume` is the one way to continue a run folder.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.errors import UserError
from pipeline.files.atomic import atomic_write_text
from pipeline.files.folders import make_folder
from pipeline.outputs.run_folder import RunFolder

log = logging.getLogger("gsplatam")

LATEST = "latest"


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
    folder = RunFolder(_named(output, name) if name else _timestamped(output, stem))
    with folder.claimed():
        if name:
            _clear_earlier_run(folder, overwrite)
        _point_latest_at(folder.path)
        yield folder


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
    found = folder.earlier_run()
    if not found:
        return
    if not overwrite:
        raise UserError(
            f"{folder.path} holds an earlier run ({', '.join(found)}): continue it with "
            f"--resume {folder.path}, replace it with --overwrite, or choose another --name"
        )
    folder.remove_earlier_run()
    log.info("--overwrite: removed the earlier run's files from %s", folder.path)


def _point_latest_at(folder: Path) -> None:
    """`latest` beside `folder` names it: a relative symlink replaced atomically, or a text file."""
    latest = folder.parent / LATEST
    staged = folder.parent / f".{LATEST}.{os.getpid()}.tmp"
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
