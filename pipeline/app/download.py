"""The `download` command: a public sequence fetched from its publisher (resumable, its SHA-256
checked or recorded) and unpacked, whole or not at all, into a folder `gsplatam run` reads."""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.files.download import fetched
from pipeline.io.files.folders import atomic_folder, make_folder
from pipeline.io.sources.datasets.catalogue import sequence_of
from pipeline.io.sources.datasets.public import MARKER, unpack

log = logging.getLogger("gsplatam")

DOWNLOADS = ".gsplatam-downloads"  # under the destination: archives, whole or in part, and their records


def download_sequence(kind: str, name: str, destination: Path, progress: bool) -> Path:
    """The folder under `destination` holding sequence `name` of `kind`, downloaded and unpacked
    unless it is there already. An archive that holds other sequences too is kept for them."""
    sequence = sequence_of(kind, name)
    target = destination / sequence.folder
    if (target / MARKER).is_file():
        log.info("%s is there already (%s)", sequence.name, target)
        return target
    if target.exists():
        raise UserError(f"{target} exists and is not a download of gsplatam: remove it or choose another destination")
    downloads = make_folder(destination / DOWNLOADS, "the downloads folder")
    archive = downloads / sequence.archive_name
    fetched(sequence.url, archive, sequence.sha256, progress)
    make_folder(target.parent, "the destination")
    log.info("unpacking %s from %s", sequence.name, archive.name)
    try:
        atomic_folder(target, lambda staged: unpack(sequence, archive, staged))
    except OSError as exc:
        raise UserError(f"cannot write {target}: {exc.strerror or exc}") from None
    if sequence.shared_archive:
        log.info("kept %s (%.1f GB) for the archive's other sequences: remove it when done", archive, _gb(archive))
    else:
        for path in (archive, archive.with_name(archive.name + ".json")):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        with contextlib.suppress(OSError):
            downloads.rmdir()  # when it holds nothing else
    return target


def _gb(path: Path) -> float:
    return path.stat().st_size / 1e9
