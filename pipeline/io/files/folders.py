"""Making the folders outputs go into, with the mistakes a user can make named, and writing a
folder of files as a whole."""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Callable
from pathlib import Path

from pipeline.errors import UserError


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
    staged, earlier = path.with_name(f".{path.name}.{tag}.tmp"), path.with_name(f".{path.name}.{tag}.old.tmp")
    staged.mkdir()  # the umask's mode, as any folder
    try:
        fill(staged)
        if path.exists():
            path.rename(earlier)
        staged.rename(path)
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        if earlier.exists() and not path.exists():
            earlier.rename(path)
        raise
    shutil.rmtree(earlier, ignore_errors=True)
