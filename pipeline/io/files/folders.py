"""Making the folders outputs go into, with the mistakes a user can make named, and writing a
folder of files as a whole."""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Callable
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.files.atomic import temporary_name


def make_folder(path: Path, what: str) -> Path:
    """Create `path` (and its parents) if missing; UserError naming `what` (e.g. "the output
    folder") and `path` when it is a file or cannot be created."""
    if path.exists() and not path.is_dir():
        raise UserError(f"{what} {path} is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {what} {path}: {exc.strerror}") from None
    return path


def atomic_folder(path: Path, fill: Callable[[Path], None]) -> None:
    """For an output of several files: `fill` writes them into a new folder beside `path`, which
    then takes `path`'s place (replacing an earlier folder there), so the folder appears complete
    or not at all; if `fill` fails (a full disk) the temporary folder goes and `path` stays as it was."""
    tag = f"{os.getpid()}.{secrets.token_hex(4)}"
    staged, earlier = temporary_name(path, tag), temporary_name(path, f"{tag}.old")
    staged.mkdir()  # the umask's mode, as any folder
    try:
        fill(staged)
        if os.path.lexists(path):
            path.rename(earlier)
        staged.rename(path)
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        if os.path.lexists(earlier) and not os.path.lexists(path):
            earlier.rename(path)
        raise
    if earlier.is_symlink():  # a link to elsewhere: the link goes, never what it points at
        earlier.unlink()
    else:
        shutil.rmtree(earlier, ignore_errors=True)


def inside(folder: Path, relative: str | Path) -> Path | None:
    """`folder / relative` where it lies in `folder` without passing through a link: a relative
    path without `..` none of whose folders on the way is a symbolic link (the last part may be
    one: it is then acted on itself, never followed). None otherwise: a path a file names (a run
    folder received from someone else) never leads this tool outside the folder."""
    parts = Path(relative).parts
    if not parts or Path(relative).is_absolute() or ".." in parts:
        return None
    path = folder
    for part in parts[:-1]:
        path = path / part
        if path.is_symlink():
            return None
    return folder.joinpath(*parts)
