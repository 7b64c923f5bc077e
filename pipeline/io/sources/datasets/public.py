"""Unpacking the public RGB-D sequences `gsplatam download` fetches (catalogue.py names them)
into a folder `gsplatam run` reads:

- TUM RGB-D (TU Munich): one .tgz per sequence, already in the TUM layout.
- Replica, as NICE-SLAM rendered it (ETH Zurich): one .zip of all eight scenes, each in the
  Replica layout (`results/`, `traj.txt`); the archive is kept for the other scenes.
- 7-Scenes (Microsoft Research): one .zip per scene holding a .zip per sequence of
  `frame-NNNNNN.{color.png,depth.png,pose.txt}`, written out in the TUM layout (depth from
  millimetres, 65535 meaning none, to TUM's 5000 units per metre; timestamps at 30 frames/s; the
  published intrinsics in intrinsics.txt); the archive is kept for the scene's other sequences.

None of the publishers gives checksums: each archive's own (gzip's CRC-32, zip's CRC-32 of
every member) is checked as it is unpacked, and its SHA-256 is recorded at its download
(`Sequence.sha256` pins one where it has been measured).
"""

from __future__ import annotations

import gzip
import json
import shutil
import tarfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import IO

import cv2
import numpy as np

from pipeline.errors import DataError
from pipeline.io.files.atomic import atomic_write_bytes, atomic_write_text
from pipeline.io.files.images import encode_depth_png
from pipeline.io.files.trajectory import tum_trajectory_text
from pipeline.io.sources.datasets.base import intrinsics_matrix, write_intrinsics_file
from pipeline.io.sources.datasets.catalogue import (
    SEVEN_SCENES_CAMERA,
    SEVEN_SCENES_FPS,
    SEVEN_SCENES_NO_DEPTH,
    Sequence,
)
from pipeline.io.sources.datasets.tum import DEPTH_SCALE as TUM_DEPTH_SCALE

MARKER = ".gsplatam-download.json"  # in an unpacked folder: where it came from (and that it is whole)


def unpack(sequence: Sequence, archive: Path, staged: Path) -> None:
    """Write `sequence` from `archive` into the empty folder `staged`, in a layout `run` reads,
    with MARKER; DataError naming the archive where it is damaged (a CRC that does not match, a
    member cut short) or lacks the sequence."""
    try:
        if sequence.kind == "tum":
            _untar(archive, sequence.member, staged)
        elif sequence.kind == "replica":
            with zipfile.ZipFile(archive) as bundle:
                _unzip(bundle, sequence.member, staged, archive)
        else:
            _seven_scenes(archive, sequence.member, staged)
    except (tarfile.TarError, zipfile.BadZipFile, gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise DataError(f"{archive} is damaged ({exc}): remove it and run the command again") from None
    marker = {"kind": sequence.kind, "name": sequence.name, "url": sequence.url}
    atomic_write_text(staged / MARKER, json.dumps(marker, indent=2) + "\n")


def _safe(name: str, prefix: str) -> PurePosixPath | None:
    """`name` relative to `prefix` (a folder of the archive), None outside it; DataError for a
    name that would leave the folder it is unpacked into."""
    path = PurePosixPath(name)
    if path.is_absolute() or ".." in path.parts:
        raise DataError(f"the archive names {name}, outside the folder it unpacks into: refused")
    parts = PurePosixPath(prefix.rstrip("/")).parts
    if path.parts[: len(parts)] != parts or len(path.parts) == len(parts):
        return None
    return PurePosixPath(*path.parts[len(parts) :])


def _untar(archive: Path, prefix: str, staged: Path) -> None:
    """The files under `prefix` of a .tgz, read to its end (gzip's CRC-32 and length checked
    there); links and devices are refused."""
    found = 0
    with tarfile.open(archive, "r:gz") as tar:
        for member in tar:
            relative = _safe(member.name, prefix)
            if relative is None or member.isdir():
                continue
            if not member.isfile():
                raise DataError(f"{archive}: {member.name} is a link or a device, not a file: refused")
            source = tar.extractfile(member)
            assert source is not None  # a regular file
            _write_member(staged / relative, source)
            found += 1
        if tar.fileobj is not None:
            while tar.fileobj.read(1 << 20):  # to the gzip stream's end, where its CRC-32 and length are checked
                pass
    if not found:
        raise DataError(f"{archive} holds no {prefix}/")


def _unzip(bundle: zipfile.ZipFile, prefix: str, staged: Path, archive: Path) -> int:
    """The files under `prefix` of a zip (each member's CRC-32 checked as it is read) -> count."""
    found = 0
    for info in bundle.infolist():
        relative = _safe(info.filename, prefix)
        if relative is None or info.is_dir():
            continue
        with bundle.open(info) as source:
            _write_member(staged / relative, source)
        found += 1
    if not found:
        raise DataError(f"{archive} holds no {prefix}/")
    return found


def _write_member(target: Path, source: IO[bytes]) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target, "wb") as out:
        shutil.copyfileobj(source, out)


def _seven_scenes(archive: Path, member: str, staged: Path) -> None:
    """A 7-Scenes sequence (the zip `member` inside the scene's zip) in the TUM layout."""
    with zipfile.ZipFile(archive) as scene:
        if member not in scene.namelist():
            held = sorted(n.rsplit("/", 1)[-1].removesuffix(".zip") for n in scene.namelist() if n.endswith(".zip"))
            raise DataError(f"{archive} holds no {member} (it holds {', '.join(held)})")
        inner = staged / ".sequence.zip"
        with scene.open(member) as source:
            _write_member(inner, source)
    with zipfile.ZipFile(inner) as sequence:
        frames = sorted(n for n in sequence.namelist() if n.endswith(".color.png"))
        if not frames:
            raise DataError(f"{archive}: {member} holds no frame-NNNNNN.color.png")
        _seven_scenes_as_tum(sequence, frames, staged)
    inner.unlink()


def _seven_scenes_as_tum(sequence: zipfile.ZipFile, colors: list[str], staged: Path) -> None:
    """Colour as is, depth rescaled to TUM's units, poses (camera-to-world) as groundtruth.txt."""
    (staged / "rgb").mkdir()
    (staged / "depth").mkdir()
    stamps, poses, rgb, depth = [], [], [], []
    for i, color_name in enumerate(colors):
        base = color_name.removesuffix(".color.png")
        stamp = f"{i / SEVEN_SCENES_FPS:.6f}"
        atomic_write_bytes(staged / "rgb" / f"{stamp}.png", sequence.read(color_name))
        atomic_write_bytes(staged / "depth" / f"{stamp}.png", _tum_depth(sequence.read(f"{base}.depth.png"), base))
        poses.append(_pose(sequence.read(f"{base}.pose.txt"), base))
        stamps.append(i / SEVEN_SCENES_FPS)
        rgb.append(f"{stamp} rgb/{stamp}.png")
        depth.append(f"{stamp} depth/{stamp}.png")
    header = "# 7-Scenes, written by gsplatam download\n# timestamp filename\n"
    atomic_write_text(staged / "rgb.txt", header + "\n".join(rgb) + "\n")
    atomic_write_text(staged / "depth.txt", header + "\n".join(depth) + "\n")
    atomic_write_text(staged / "groundtruth.txt", tum_trajectory_text(np.array(stamps), np.stack(poses)))
    write_intrinsics_file(staged, intrinsics_matrix(*SEVEN_SCENES_CAMERA))


def _tum_depth(png: bytes, name: str) -> bytes:
    """7-Scenes' depth PNG (uint16 millimetres, 65535: none) as TUM's (uint16 at 5000 per metre)."""
    raw = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        raise DataError(f"{name}.depth.png is not a 16-bit depth image")
    metres = np.where(raw == SEVEN_SCENES_NO_DEPTH, 0, raw).astype(np.float64) / 1000.0
    return encode_depth_png(metres, TUM_DEPTH_SCALE)


def _pose(text: bytes, name: str) -> np.ndarray:
    """A 7-Scenes pose file: a 4x4 camera-to-world matrix, a row a line."""
    try:
        rows = [[float(v) for v in line.split()] for line in text.decode().splitlines() if line.strip()]
        pose = np.array(rows, dtype=np.float64)
    except (ValueError, UnicodeDecodeError):
        pose = np.zeros(0)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise DataError(f"{name}.pose.txt: expected a 4x4 camera-to-world matrix of finite numbers")
    return pose
