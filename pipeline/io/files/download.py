"""Fetching a large file over HTTP(S), resumable: the bytes go to `<name>.part` beside the file,
and a later call asks the server for the rest only (an HTTP Range request, guarded by If-Range
so that a file changed on the server starts over). Once whole, its size is checked against the
server's and its SHA-256 against the one expected (or, where none is known, recorded beside it in
`<name>.json` and checked at every later use)."""

from __future__ import annotations

import contextlib
import hashlib
import http.client
import json
import logging
import re
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO

from tqdm import tqdm

from pipeline.errors import DataError, UserError
from pipeline.io.files.atomic import atomic_write_text

log = logging.getLogger("gsplatam")

CHUNK = 1 << 20  # bytes read and written at a time
TIMEOUT_S = 60.0  # a server silent this long is given up on (what came is kept)
USER_AGENT = "gsplatam-download"


@dataclass
class Record:
    """`<name>.json` beside a download: where it came from, the server's validator and size,
    and, once whole, its SHA-256."""

    url: str
    validator: str = ""  # the server's ETag (or Last-Modified): If-Range sends it back
    size: int | None = None  # bytes, as the server announced them
    sha256: str = ""  # once whole

    @staticmethod
    def read(path: Path) -> Record | None:
        try:
            table = json.loads(path.read_text())
            return Record(str(table["url"]), str(table["validator"]), table["size"], str(table["sha256"]))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def write(self, path: Path) -> None:
        atomic_write_text(path, json.dumps(asdict(self), indent=2) + "\n")


def fetched(url: str, path: Path, sha256: str = "", progress: bool = True) -> str:
    """`path` holding the file at `url`, downloaded (or its download resumed) unless it is there
    whole already -> its SHA-256. UserError for a server that cannot be reached or refuses (what
    came is kept for the next call), DataError for a file whose size or SHA-256 is not the one
    expected (it is removed)."""
    record_path = path.with_name(path.name + ".json")
    record = Record.read(record_path)
    if path.is_file() and record is not None and record.url == url and record.sha256:
        if record.size is not None and path.stat().st_size != record.size:
            raise DataError(
                f"{path} is {path.stat().st_size} bytes, {record.size} were downloaded: remove it and run again"
            )
        if sha256 and record.sha256 != sha256:
            raise DataError(f"{path} has SHA-256 {record.sha256}, expected {sha256}: remove it and run again")
        return record.sha256
    part = path.with_name(path.name + ".part")
    if record is None or record.url != url:
        record = Record(url)
        with contextlib.suppress(FileNotFoundError):
            part.unlink()
    _download(url, part, record, record_path, progress)
    digest = _sha256(part)
    if sha256 and digest != sha256:
        for leftover in (part, record_path):
            with contextlib.suppress(FileNotFoundError):
                leftover.unlink()
        raise DataError(f"{url} arrived with SHA-256 {digest}, expected {sha256}: removed; run the command again")
    part.replace(path)
    record.sha256 = digest
    record.write(record_path)
    if not sha256:
        log.info("%s: SHA-256 %s (recorded in %s; checked at every later use)", path.name, digest, record_path.name)
    return digest


def _download(url: str, part: Path, record: Record, record_path: Path, progress: bool) -> None:
    """Fill `part` with the bytes of `url`, from where an earlier call stopped where the server
    still has the same file; `record` notes the server's validator and size as they come."""
    offset = part.stat().st_size if part.is_file() else 0
    headers = {"User-Agent": USER_AGENT}
    if offset and record.validator:
        headers |= {"Range": f"bytes={offset}-", "If-Range": record.validator}
    try:
        with _opened(url, headers) as response:
            status = response.status
            if status == 206 and _range_start(response.headers.get("Content-Range", "")) == offset:
                size = _total(response.headers.get("Content-Range", ""))
                log.info("resuming the download of %s at %.1f MB", url, offset / 1e6)
            else:  # the whole file (a first call, a server without ranges, or a file that changed)
                offset, size = 0, _int(response.headers.get("Content-Length"))
            record.validator = response.headers.get("ETag") or response.headers.get("Last-Modified") or ""
            record.size = size
            record.write(record_path)
            with open(part, "ab" if offset else "wb") as out:
                _copy(response, out, offset, size, url, progress)
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and record.size is not None and offset == record.size:
            return  # the part is whole already: a call that stopped just after the last byte
        raise UserError(f"cannot download {url}: HTTP {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", None) or getattr(exc, "strerror", None) or exc
        got = part.stat().st_size if part.is_file() else 0
        raise UserError(
            f"cannot download {url}: {reason} ({got / 1e6:.1f} MB kept: run the same command again to resume)"
        ) from None
    got = part.stat().st_size
    if record.size is not None and got != record.size:
        raise UserError(
            f"the download of {url} ended at {got} of {record.size} bytes (kept: run the same command again to resume)"
        )


@contextlib.contextmanager
def _opened(url: str, headers: dict[str, str]) -> Iterator[http.client.HTTPResponse]:
    request = urllib.request.Request(url, headers=headers)
    with urllib.request.urlopen(request, timeout=TIMEOUT_S) as response:
        yield response


def _copy(response: IO[bytes], out: IO[bytes], offset: int, size: int | None, url: str, progress: bool) -> None:
    """Stream the response's body into `out`, flushed as it goes (a kill keeps what came)."""
    name = url.rsplit("/", 1)[-1]
    with tqdm(total=size, initial=offset, unit="B", unit_scale=True, desc=name, disable=not progress) as bar:
        try:
            while chunk := response.read(CHUNK):
                out.write(chunk)
                bar.update(len(chunk))
        except KeyboardInterrupt:
            out.flush()
            log.info("download stopped at %.1f MB: run the same command again to resume", out.tell() / 1e6)
            raise


def _range_start(content_range: str) -> int | None:
    match = re.match(r"bytes (\d+)-\d+/(\d+|\*)", content_range)
    return int(match.group(1)) if match else None


def _total(content_range: str) -> int | None:
    match = re.match(r"bytes \d+-\d+/(\d+)", content_range)
    return int(match.group(1)) if match else None


def _int(text: str | None) -> int | None:
    return int(text) if text is not None and text.isdigit() else None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()
