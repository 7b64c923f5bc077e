"""`gsplatam download` against a local HTTP server the test starts (port 0, no network): the
archives are made here in the publishers' layouts; resuming, checksums, damaged archives."""

from __future__ import annotations

import hashlib
import io
import tarfile
import threading
import zipfile
from collections.abc import Iterator
from dataclasses import replace
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.app.cli import main
from pipeline.config import DatasetConfig
from pipeline.io.files.trajectory import matrix_to_quat_xyzw
from pipeline.io.sources.datasets import catalogue as catalogue_module
from pipeline.io.sources.datasets.catalogue import Sequence
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.public import MARKER


class Archives(ThreadingHTTPServer):
    """Files by path, served with Range and If-Range as a publisher's server does; `cut_after`
    ends the first response of a path after that many bytes (a dropped connection)."""

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), Handler)
        self.files: dict[str, bytes] = {}
        self.cut_after: dict[str, int] = {}
        self.requests: list[tuple[str, str | None]] = []  # (path, Range header)

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/{name}"


class Handler(BaseHTTPRequestHandler):
    server: Archives

    def log_message(self, format: str, *args: object) -> None:  # quiet
        pass

    def do_GET(self) -> None:
        name = self.path.lstrip("/")
        self.server.requests.append((name, self.headers.get("Range")))
        data = self.server.files.get(name)
        if data is None:
            self.send_error(404)
            return
        etag = '"' + hashlib.sha1(data).hexdigest() + '"'
        start = 0
        wanted = self.headers.get("Range")
        if wanted and self.headers.get("If-Range") in (None, etag):
            start = int(wanted.removeprefix("bytes=").split("-")[0])
            if start >= len(data):
                self.send_error(416)
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            self.send_response(200)
        body = data[start:]
        self.send_header("Content-Length", str(len(body)))
        self.send_header("ETag", etag)
        self.end_headers()
        cut = self.server.cut_after.pop(name, None)
        self.wfile.write(body if cut is None else body[:cut])


@pytest.fixture
def archives() -> Iterator[Archives]:
    server = Archives()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()


def _serve(archives: Archives, monkeypatch: pytest.MonkeyPatch, kind: str, sequence: Sequence, data: bytes) -> None:
    """`sequence` (its archive `data`) in the catalogue, published by the local server."""
    archives.files[sequence.archive_name] = data
    known = catalogue_module.catalogue()
    local = replace(sequence, url=archives.url(sequence.archive_name))
    monkeypatch.setattr(catalogue_module, "catalogue", lambda: {**known, kind: {sequence.name: local}})


def _tgz(folder: Path, root: str) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        tar.add(folder, arcname=root)
    return buffer.getvalue()


TUM = Sequence("tum", "fr1/room", "", "rgbd_dataset_freiburg1_room", "rgbd_dataset_freiburg1_room", False)


def test_a_tum_sequence_is_downloaded_resumed_after_a_dropped_connection_and_unpacked(
    tum_seq: Path, tmp_path: Path, archives: Archives, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    data = _tgz(tum_seq, TUM.folder)
    sequence = replace(TUM, url=f"x/{TUM.folder}.tgz")
    _serve(archives, monkeypatch, "tum", sequence, data)
    archives.cut_after[sequence.archive_name] = len(data) // 2
    dest = tmp_path / "data"
    assert main(["download", "tum", "fr1/room", str(dest), "--quiet"]) == 2  # the connection dropped midway
    assert "run the same command again to resume" in capsys.readouterr().err.strip().splitlines()[-1]
    part = dest / ".gsplatam-downloads" / f"{TUM.folder}.tgz.part"
    assert part.stat().st_size == len(data) // 2 and not (dest / TUM.folder).exists()
    assert main(["download", "tum", "freiburg1_room", str(dest), "--quiet"]) == 0  # another spelling of it
    assert archives.requests[-1] == (sequence.archive_name, f"bytes={len(data) // 2}-")  # only the rest
    folder = dest / TUM.folder
    assert "next:\n  " in capsys.readouterr().out and (folder / MARKER).is_file()
    ours, theirs = open_dataset(DatasetConfig(path=str(folder))), open_dataset(DatasetConfig(path=str(tum_seq)))
    assert len(ours) == len(theirs) and (ours.decode(ours.refs[2]).depth == theirs.decode(theirs.refs[2]).depth).all()
    assert not (dest / ".gsplatam-downloads").exists()  # one sequence's archive: removed once unpacked
    requests = len(archives.requests)
    assert main(["download", "tum", "fr1/room", str(dest), "--quiet"]) == 0  # there already: nothing fetched
    assert len(archives.requests) == requests


def test_a_download_whose_checksum_differs_is_removed_and_nothing_unpacked(
    tum_seq: Path, tmp_path: Path, archives: Archives, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    data = _tgz(tum_seq, TUM.folder)
    _serve(archives, monkeypatch, "tum", replace(TUM, url=f"x/{TUM.folder}.tgz", sha256="0" * 64), data)
    dest = tmp_path / "data"
    assert main(["download", "tum", "fr1/room", str(dest), "--quiet"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"arrived with SHA-256 {hashlib.sha256(data).hexdigest()}, expected {'0' * 64}: removed" in line
    assert list((dest / ".gsplatam-downloads").iterdir()) == [] and not (dest / TUM.folder).exists()


def test_a_damaged_archive_is_named_and_leaves_no_folder(
    tum_seq: Path, tmp_path: Path, archives: Archives, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    data = bytearray(_tgz(tum_seq, TUM.folder))
    data[len(data) // 2] ^= 0xFF  # a bit flipped on the way: gzip's CRC-32 (or its inflation) says so
    _serve(archives, monkeypatch, "tum", replace(TUM, url=f"x/{TUM.folder}.tgz"), bytes(data))
    dest = tmp_path / "data"
    assert main(["download", "tum", "fr1/room", str(dest), "--quiet"]) == 2
    assert "is damaged" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (dest / TUM.folder).exists() and not list(dest.glob(".*.tmp"))


def test_a_replica_scene_is_taken_out_of_the_archive_of_all_scenes(
    replica_seq: Path, tmp_path: Path, archives: Archives, monkeypatch: pytest.MonkeyPatch
) -> None:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as bundle:
        for scene in ("room0", "office0"):
            for path in sorted(replica_seq.rglob("*")):
                if path.is_file():
                    bundle.write(path, f"Replica/{scene}/{path.relative_to(replica_seq)}")
        bundle.writestr("Replica/cam_params.json", "{}")
    sequence = Sequence("replica", "office0", "x/Replica.zip", "Replica/office0", "Replica/office0", True)
    _serve(archives, monkeypatch, "replica", sequence, buffer.getvalue())
    dest = tmp_path / "data"
    assert main(["download", "replica", "office0", str(dest), "--quiet"]) == 0
    dataset = open_dataset(DatasetConfig(path=str(dest / "Replica" / "office0")))
    assert dataset.format == "replica" and len(dataset) == len(open_dataset(DatasetConfig(path=str(replica_seq))))
    assert not (dest / "Replica" / "room0").exists()
    assert (dest / ".gsplatam-downloads" / "Replica.zip").is_file()  # kept for the other scenes


def test_a_7scenes_sequence_becomes_a_tum_folder_in_metres(
    tmp_path: Path, archives: Archives, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    rng = np.random.default_rng(0)
    depth_mm = rng.integers(500, 4000, size=(48, 64)).astype(np.uint16)
    depth_mm[0, :8] = 65535  # 7-Scenes' "no depth"
    poses = []
    inner = io.BytesIO()
    with zipfile.ZipFile(inner, "w") as sequence_zip:
        for i in range(3):
            pose = np.eye(4)
            pose[:3, 3] = [0.1 * i, 0.0, 0.02 * i]
            poses.append(pose)
            color = rng.integers(0, 255, size=(48, 64, 3)).astype(np.uint8)
            sequence_zip.writestr(f"seq-02/frame-{i:06d}.color.png", cv2.imencode(".png", color)[1].tobytes())
            sequence_zip.writestr(f"seq-02/frame-{i:06d}.depth.png", cv2.imencode(".png", depth_mm)[1].tobytes())
            sequence_zip.writestr(f"seq-02/frame-{i:06d}.pose.txt", "\n".join(" ".join(map(str, r)) for r in pose))
    outer = io.BytesIO()
    with zipfile.ZipFile(outer, "w") as scene:
        scene.writestr("chess/seq-02.zip", inner.getvalue())
        scene.writestr("chess/TrainSplit.txt", "sequence1\n")
    base = catalogue_module.catalogue()["7scenes"]["chess"]
    _serve(archives, monkeypatch, "7scenes", replace(base, url="x/chess.zip"), outer.getvalue())
    dest = tmp_path / "data"
    assert main(["download", "7scenes", "chess/seq-05", str(dest), "--quiet"]) == 2  # not in the archive
    assert "holds no chess/seq-05.zip (it holds seq-02)" in capsys.readouterr().err.strip().splitlines()[-1]
    assert main(["download", "7scenes", "chess/seq-02", str(dest), "--quiet"]) == 0
    dataset = open_dataset(DatasetConfig(path=str(dest / "7scenes_chess_seq-02")))
    assert dataset.format == "tum" and len(dataset) == 3
    frame = dataset.decode(dataset.refs[1])
    expected = np.where(depth_mm == 65535, 0, depth_mm) / 1000.0
    assert np.abs(frame.depth - expected).max() <= 1 / 5000 / 2 + 1e-6 and (frame.depth[0, :8] == 0).all()
    np.testing.assert_allclose(frame.intrinsics[0, 0], 585.0)
    np.testing.assert_allclose(frame.c2w_gt[:3, 3], [0.1, 0.0, 0.02], atol=1e-6)  # relative to the first pose
    assert np.allclose(matrix_to_quat_xyzw(frame.c2w_gt[:3, :3]), [0, 0, 0, 1])


def test_names_are_listed_and_a_wrong_one_is_answered_with_the_nearest(capsys) -> None:
    assert main(["download", "tum"]) == 0
    assert "fr1/desk" in capsys.readouterr().out
    assert main(["download", "tum", "fr1/dsek", "--quiet"]) == 2
    assert "unknown tum sequence 'fr1/dsek': did you mean 'fr1/desk'?" in capsys.readouterr().err
    assert main(["download", "replica", "room9", "--quiet"]) == 2
    assert "did you mean 'room0'" in capsys.readouterr().err
