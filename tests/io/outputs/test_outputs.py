"""What a run folder holds under faults: atomic sets of files, a full disk, a cut frames.csv."""

from __future__ import annotations

import csv
import errno
import logging
import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import IO

import numpy as np
import pytest
import torch
from conftest import make_checkpoint

from pipeline.errors import OutputError
from pipeline.io.files import atomic
from pipeline.io.files.atomic import atomic_export, atomic_write_all, bytes_writer, current_umask
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.frame_row import COLUMNS, EARLIER_WIDTH, FrameRow
from pipeline.io.outputs.periodic_save import PeriodicSave
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.render.types import Gaussians
from pipeline.slam.state import Checkpoint


def _enospc() -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _disk_full(f: IO[bytes]) -> None:
    f.write(b"half a file")
    raise _enospc()


def test_a_full_disk_replaces_no_file_of_a_set_and_leaves_no_temporary_file(tmp_path: Path) -> None:
    first, second = tmp_path / "a.txt", tmp_path / "b.txt"
    atomic_write_all({first: bytes_writer(b"old a"), second: bytes_writer(b"old b")})
    with pytest.raises(OSError, match="No space left"):
        atomic_write_all({first: bytes_writer(b"new a"), second: _disk_full})
    assert (first.read_bytes(), second.read_bytes()) == (b"old a", b"old b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def test_a_full_disk_at_fsync_leaves_no_temporary_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int) -> None:
        raise _enospc()

    monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(OSError):
        atomic.atomic_write_text(tmp_path / "metrics.json", "{}")
    assert list(tmp_path.iterdir()) == []


ROOM = RunDescription("room")


def _row(index: int) -> FrameRow:
    """A frames.csv line of zeros but for its index."""
    return FrameRow(index, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0, 0.0, "", "", False, 0, None, None)


def _checkpoint(frames: int) -> Checkpoint:
    n = 8
    gaussians = Gaussians(torch.zeros(n, 3), torch.ones(n, 4), torch.zeros(n, 1), torch.zeros(n), torch.rand(n, 3))
    return make_checkpoint(gaussians, [], torch.eye(4).repeat(frames, 1, 1))


def test_a_full_disk_keeps_the_last_complete_save(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = RunFolder(tmp_path)
    folder.write_state(_checkpoint(2), ROOM, np.array([0.0, 0.1]), None)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real = atomic._write_temporary

    def full_at_the_map(path: Path, write: atomic.Writer) -> str:
        if path.name == "map.ply":
            raise _enospc()
        return real(path, write)

    monkeypatch.setattr(atomic, "_write_temporary", full_at_the_map)
    with pytest.raises(OSError):
        folder.write_state(_checkpoint(3), ROOM, np.array([0.0, 0.1, 0.2]), None)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # trajectory and checkpoint too
    assert folder.read_checkpoint()[0].frames_done == 2


def test_a_save_killed_between_replacements_leaves_the_checkpoint_behind_never_ahead(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = RunFolder(tmp_path)
    folder.write_state(_checkpoint(2), ROOM, np.array([0.0, 0.1]), None)
    real = atomic.os.replace
    replaced: list[str] = []

    def killed_at_the_checkpoint(source: str, target: Path) -> None:
        if Path(target).name == "checkpoint.safetensors":
            raise KeyboardInterrupt  # stands for SIGKILL: nothing after it is replaced
        replaced.append(Path(target).name)
        real(source, target)

    monkeypatch.setattr(atomic.os, "replace", killed_at_the_checkpoint)
    with pytest.raises(KeyboardInterrupt):
        folder.write_state(_checkpoint(3), ROOM, np.array([0.0, 0.1, 0.2]), np.eye(4).repeat(3, 0).reshape(3, 4, 4))
    assert {"trajectory.txt", "map.ply", "groundtruth.txt"} <= set(replaced)  # every other file went first
    assert folder.read_checkpoint()[0].frames_done == 2
    assert len(read_tum_trajectory(folder.trajectory)[0]) == 3  # one save ahead: a resume rewrites it


class _Slam:
    """What PeriodicSave reads of SLAM."""

    def __init__(self) -> None:
        self.frames = 0

    @property
    def gaussians(self) -> Gaussians:
        return self.checkpoint().gaussians

    def checkpoint(self) -> Checkpoint:
        return _checkpoint(self.frames)


def _result(index: int):  # type: ignore[no-untyped-def]
    from pipeline.slam.splatam import FrameResult

    return FrameResult(index, 0.1 * index, torch.eye(4), {}, 8, 0, 0.0, 1.0)


@pytest.mark.parametrize("stop_on_failure", [False, True])
def test_a_failing_save_is_reported_once_and_stops_only_a_run_that_asks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, stop_on_failure: bool
) -> None:
    folder = RunFolder(tmp_path)
    saver = PeriodicSave(folder, ROOM, every_s=0.0, stop_on_failure=stop_on_failure)
    slam = _Slam()
    real = RunFolder.write_state
    full = [False]

    def write_state(self, *args) -> None:  # type: ignore[no-untyped-def]
        if full[0]:
            raise _enospc()
        real(self, *args)

    monkeypatch.setattr(RunFolder, "write_state", write_state)

    def frame(index: int) -> None:
        slam.frames = index + 1
        saver(slam, None, _result(index))  # type: ignore[arg-type]
        saver.wait()  # one save per frame in this test

    with caplog.at_level(logging.INFO, "gsplatam"):
        frame(0)
        full[0] = True
        frame(1)
        if stop_on_failure:
            with pytest.raises(OutputError, match="No space left on device"):
                frame(2)
        else:
            frame(2)
            frame(3)
            full[0] = False
            saver.save_now(slam.checkpoint())
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1 and "the last complete save (1 frames) is kept" in errors[0].getMessage()
    if stop_on_failure:
        assert "No space left" in saver.error and saver.saved_frames == 1
        assert folder.read_checkpoint()[0].frames_done == 1
    if not stop_on_failure:  # the daemon's case: SLAM went on, and the disk has room again
        assert saver.error == "" and folder.read_checkpoint()[0].frames_done == 4
        assert "works again" in caplog.text


def test_a_final_save_that_fails_says_what_is_kept(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    saver = PeriodicSave(RunFolder(tmp_path), ROOM, every_s=1e9)

    def full(*args) -> None:  # type: ignore[no-untyped-def]
        raise _enospc()

    monkeypatch.setattr(RunFolder, "write_state", full)
    with pytest.raises(OutputError, match="No space left on device; nothing is saved yet"):
        saver.save_now(_Slam().checkpoint())


def test_frames_csv_keeps_the_rows_of_the_checkpointed_frames_and_drops_a_cut_line(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path)
    row = replace(_row(0), lost="pose jumped 0.4 m, twice")
    for i in range(5):
        folder.append_frame(replace(row, index=i))
    folder.close()
    with open(folder.frames_csv, "a") as f:
        f.write("5,0.1,0.2")  # a kill or a full disk in the middle of a line
    folder.keep_frames(3)
    lines = folder.frames_csv.read_text().splitlines()
    assert lines[0] == ",".join(COLUMNS) and [line.split(",")[0] for line in lines[1:]] == ["0", "1", "2"]
    folder.append_frame(replace(row, index=3))
    folder.close()
    assert folder.frames_csv.read_text().splitlines()[-1].startswith("3,")


def test_a_resume_keeps_the_rows_of_an_earlier_frames_csv_layout(tmp_path: Path) -> None:
    """A run folder written before the solve's columns existed: its rows are kept on resume,
    padded with empty cells under today's header, and the run goes on appending whole rows."""
    folder = RunFolder(tmp_path)
    earlier = [",".join(COLUMNS[:EARLIER_WIDTH])] + [
        ",".join(str(c) for c in _row(i).cells()[:EARLIER_WIDTH]) for i in range(3)
    ]
    folder.frames_csv.write_text("\r\n".join(earlier) + "\r\n")
    folder.keep_frames(2)
    folder.append_frame(_row(2))
    folder.close()
    with open(folder.frames_csv, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == list(COLUMNS) and [row[0] for row in rows[1:]] == ["0", "1", "2"]
    assert {len(row) for row in rows} == {len(COLUMNS)} and rows[1][EARLIER_WIDTH:] == [""] * (
        len(COLUMNS) - EARLIER_WIDTH
    )


def test_every_frames_csv_line_is_on_disk_as_soon_as_it_is_written(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path)
    folder.append_frame(_row(1))
    assert len(folder.frames_csv.read_text().splitlines()) == 2  # read by another reader, before any close
    folder.close()


@pytest.fixture(params=[0o022, 0o027], ids=["umask022", "umask027"])
def umask(request: pytest.FixtureRequest) -> Iterator[int]:
    earlier = os.umask(request.param)
    yield request.param
    os.umask(earlier)


def test_written_files_and_folders_have_the_mode_the_umask_leaves(umask: int, tmp_path: Path) -> None:
    atomic.atomic_write_text(tmp_path / "metrics.json", "{}")
    atomic_write_all({tmp_path / "map.ply": bytes_writer(b"ply"), tmp_path / "trajectory.txt": bytes_writer(b"")})
    folder = atomic.temporary_folder(tmp_path, ".room.")
    modes = {p.name: p.stat().st_mode & 0o777 for p in (tmp_path / "metrics.json", tmp_path / "map.ply", folder)}
    assert modes == {"metrics.json": 0o666 & ~umask, "map.ply": 0o666 & ~umask, folder.name: 0o777 & ~umask}


def test_the_umask_is_read_without_proc_too(umask: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(atomic, "Path", lambda _: Path("/nonexistent/status"))
    assert atomic.current_umask() == umask
    assert os.umask(umask) == umask  # left as it was


def test_a_library_export_never_writes_through_a_link_planted_at_a_temporary_name(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    target = tmp_path / "trace.json"
    (tmp_path / f".{target.name}.{os.getpid()}.tmp").symlink_to(victim)  # the name the writer once used

    def export(path: Path) -> None:
        with open(path, "w") as f:  # as the torch profiler writes its trace: by name
            f.write("{}")

    atomic_export(target, export)
    assert victim.read_text() == "keep me"
    assert target.read_text() == "{}" and not target.is_symlink()
    assert target.stat().st_mode & 0o777 == 0o666 & ~current_umask()
