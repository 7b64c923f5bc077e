"""Making the folders outputs go into, with the mistakes a user can make named."""

from __future__ import annotations

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
