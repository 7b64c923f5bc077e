"""exports.json in a run folder: each export's path and the map it came from, so that a resume
that moves the map on marks them stale and `--overwrite` removes those inside the folder.

The file comes from disk, perhaps from someone else: every entry is checked (an object naming a
path, its counts whole numbers), and a record that is not sound is reported once and rebuilt:
its sound entries kept, and the exports present at their default places recorded again, marked
stale (the map they came from is unknown). A recorded path is followed only inside the folder
and never through a link (`folders.inside`). Every change is made under an exclusive lock on the
run folder itself (flock on the folder's descriptor, so no lock file is added), so exports
started at once each keep their entry.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.files.folders import inside

log = logging.getLogger("gsplatam")

NAME = "exports.json"
Entry = dict[str, Any]
# the fields of an entry this version reads, and the JSON types each may take ("path" is required;
# fields of a later version are kept as they are)
FIELDS: dict[str, tuple[type, ...]] = {
    "path": (str,),
    "frames": (int,),
    "frames_mapped": (int,),
    "gaussians": (int,),
    "map_version": (int, type(None)),
    "stale": (str,),
}
REBUILT = f"recorded again from the file present ({NAME} was not sound): the map it came from is unknown"


class ExportsRecord:
    """exports.json of the run folder `folder`; `defaults`: format -> the path (in the folder)
    where its export is written by default."""

    def __init__(self, folder: Path, defaults: Mapping[str, str]) -> None:
        self.folder = folder
        self.path = folder / NAME
        self.defaults = defaults
        self._reported = False

    def read(self) -> tuple[dict[str, Entry], bool]:
        """-> (format -> entry; whether the record on disk was not sound and this is it rebuilt).
        {} where there is none."""
        try:
            entries, problem = _sound(self.path.read_text())
        except FileNotFoundError:
            return {}, False
        except (OSError, UnicodeDecodeError) as exc:
            entries, problem = {}, f"cannot be read ({getattr(exc, 'strerror', None) or exc})"
        if not problem:
            return entries, False
        if not self._reported:
            log.warning("%s %s: rebuilt from the exports present", self.path, problem)
            self._reported = True
        for fmt, default in self.defaults.items():
            if fmt not in entries and os.path.lexists(self.folder / default):
                entries[fmt] = {"path": default, "stale": REBUILT}
        return entries, True

    def write(self, entries: Mapping[str, Entry]) -> None:
        atomic_write_text(self.path, text_of(entries))

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Held while the record is read, changed and written (by an export or a run's save)."""
        fd = os.open(self.folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            with contextlib.suppress(OSError):  # a file system without flock: no lock, as before
                fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # closing the descriptor releases the lock

    def inside(self) -> list[tuple[str, Path]]:
        """(format, path) of every export recorded inside the folder, reached without a link. A
        path that would lead out of it (through a link, or `..`) is reported and left alone; an
        absolute one is an export the user put elsewhere, left alone."""
        found = []
        for fmt, entry in self.read()[0].items():
            recorded = Path(entry["path"])
            if recorded.is_absolute():
                continue
            path = inside(self.folder, recorded)
            if path is None:
                log.warning(
                    "%s names %s for '%s', which leads out of %s (through a link or '..'): left alone",
                    self.path, recorded, fmt, self.folder,
                )  # fmt: skip
            else:
                found.append((fmt, path))
        return found


def text_of(entries: Mapping[str, Entry]) -> str:
    return json.dumps(entries, indent=2, sort_keys=True) + "\n"


def _sound(text: str) -> tuple[dict[str, Entry], str]:
    """-> (the sound entries of exports.json's text; what is wrong with it, empty when nothing)."""
    try:
        value = json.loads(text)
    except ValueError:
        return {}, "is not JSON"
    if not isinstance(value, dict):
        return {}, f"is a JSON {type(value).__name__}, not an object of exports"
    entries, problems = {}, []
    for fmt, entry in value.items():
        if why := _problem(entry):
            problems.append(f"'{fmt}' {why}")
        else:
            entries[fmt] = entry
    return entries, f"holds entries that are not exports ({'; '.join(problems)})" if problems else ""


def _problem(entry: Any) -> str:
    """What makes `entry` not an export's entry; empty when it is one."""
    if not isinstance(entry, dict):
        return f"is {json.dumps(entry)[:40]}, not an object"
    if not isinstance(entry.get("path"), str) or not entry["path"]:
        return "names no path"
    for key, value in entry.items():
        kinds = FIELDS.get(key)
        if kinds is None:
            continue
        if isinstance(value, bool) or not isinstance(value, kinds) or (isinstance(value, int) and value < 0):
            return f"has {key} {json.dumps(value)[:40]}"
    return ""
