"""Run folders: a fresh one per run, never an earlier run's; one writer at a time."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT

from pipeline.app.cli import main
from pipeline.errors import UserError
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_folders import LATEST, new_run_folder
from pipeline.io.outputs.run_lock import RunFolderBusy, RunLock


def test_runs_without_a_name_get_fresh_folders_and_latest_points_at_the_newest(tmp_path: Path) -> None:
    with new_run_folder(tmp_path, "room_tiny") as claimed:
        first = claimed.path
        claimed.metrics.write_text("{}")
        claimed.checkpoint.write_text("saved")
    with new_run_folder(tmp_path, "room_tiny") as claimed:
        second = claimed.path
        claimed.checkpoint.write_text("saved")
    assert first != second and first.name.startswith("room_tiny-") and second.name.startswith(first.name[:18])
    assert (first / "metrics.json").read_text() == "{}"  # the earlier run is untouched
    assert (tmp_path / LATEST).resolve() == second.resolve()


def test_latest_is_a_text_file_where_symlinks_fail(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_symlinks(*args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        raise OSError("symlinks not supported")

    monkeypatch.setattr(os, "symlink", no_symlinks)
    with new_run_folder(tmp_path, "room_tiny") as folder:
        folder.checkpoint.write_text("saved")
    assert (tmp_path / LATEST).read_text().strip() == folder.path.name
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


def test_a_named_folder_with_an_earlier_run_is_refused_unless_overwrite(tmp_path: Path) -> None:
    folder = tmp_path / "mine"
    folder.mkdir()
    for name in ("metrics.json", "map.ply", "trace.json", "notes.txt"):
        (folder / name).write_text("earlier")
    RunFolder(folder).mark()
    with pytest.raises(UserError, match=r"mine holds an earlier run \(metrics.json, map.ply, trace.json\).*--resume"):
        with new_run_folder(tmp_path, "room_tiny", "mine"):
            pass
    assert (folder / "metrics.json").read_text() == "earlier"
    with new_run_folder(tmp_path, "room_tiny", "mine", overwrite=True) as same:
        assert same.path == folder
        assert sorted(p.name for p in folder.iterdir()) == [
            ".gsplatam-run",
            ".lock",
            "notes.txt",
        ]  # the user's own file stays


def test_overwrite_removes_the_recording_and_the_exports_too_and_nothing_of_the_users(tmp_path: Path) -> None:
    folder = tmp_path / "mine"
    written = ["metrics.json", "map.splat", "mesh.ply", "recording/rgb.txt", "recording/rgb/000000.png",
               "recording/depth/000000.png", "nerfstudio/transforms.json", "nerfstudio/images/frame_000000.png"]  # fmt: skip
    for name in [*written, "recording/notes.txt", "nerfstudio/depth/.frame_000001.png.x1.tmp",
                 ".nerfstudio.1.ab.tmp/images/frame_000000.png"]:  # fmt: skip
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text("earlier")
    RunFolder(folder).mark()
    with pytest.raises(UserError, match=r"\(metrics.json, recording, nerfstudio, map.splat, mesh.ply\)"):
        with new_run_folder(tmp_path, "room_tiny", "mine"):
            pass
    with new_run_folder(tmp_path, "room_tiny", "mine", overwrite=True):
        left = sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))
    assert left == [
        ".gsplatam-run",
        ".lock",
        "recording",
        "recording/notes.txt",
    ]  # the user's file, in the folder it needs


def test_the_pointer_name_is_refused_as_a_run_name(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="'latest' names the pointer"):
        with new_run_folder(tmp_path, "room_tiny", LATEST):
            pass


def test_the_cli_refuses_to_run_into_an_earlier_run(replica_seq: Path, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "out" / "r"
    folder.mkdir(parents=True)
    (folder / "checkpoint.safetensors").write_bytes(b"an earlier run's")
    RunFolder(folder).mark()
    code = main(["run", str(replica_seq), "--output", str(tmp_path / "out"), "--name", "r", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "holds an earlier run (checkpoint.safetensors)" in err[-1] and "--overwrite" in err[-1]
    assert (folder / "checkpoint.safetensors").read_bytes() == b"an earlier run's"
    assert main(["run", "--resume", str(folder), "--overwrite", "--quiet"]) == 2


def _hold_lock(folder: Path) -> subprocess.Popen[str]:
    """Another process holding `folder`'s lock until its stdin closes."""
    script = (
        "import sys; from pathlib import Path; from pipeline.io.outputs.run_lock import RunLock\n"
        f"with RunLock(Path({str(folder)!r})):\n    print('locked', flush=True); sys.stdin.read()\n"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", script], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
    return holder


def test_a_second_process_is_refused_a_locked_folder_and_told_the_holder(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    folder.mkdir()
    holder = _hold_lock(folder)
    try:
        with pytest.raises(
            RunFolderBusy, match=rf"{folder} is being written by another gsplatam process \(pid {holder.pid}\)"
        ):
            with RunLock(folder):
                pass
    finally:
        holder.kill()  # a holder that dies without cleaning up: the kernel frees the lock
        holder.wait()
    with RunLock(folder):  # the lock file left behind blocks nobody
        assert (folder / ".lock").read_text().strip() == str(os.getpid())


@pytest.mark.parametrize("command", ["run", "serve"])
def test_run_and_serve_refuse_a_folder_another_process_writes(
    command: str, replica_seq: Path, tmp_path: Path, capsys
) -> None:
    folder = tmp_path / "out" / "shared"
    folder.mkdir(parents=True)
    holder = _hold_lock(folder)
    source = [str(replica_seq)] if command == "run" else ["--record3d", "http://127.0.0.1:9"]
    try:
        code = main([command, *source, "--output", str(tmp_path / "out"), "--name", "shared", "--quiet"])
    finally:
        holder.kill()
        holder.wait()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and f"pid {holder.pid}" in err[-1] and str(folder) in err[-1]
    assert sorted(p.name for p in folder.iterdir()) == [".lock"]  # nothing written


def test_output_that_is_a_file_is_refused(tmp_path: Path, capsys) -> None:
    output = tmp_path / "afile"
    output.write_text("x")
    assert main(["run", "--output", str(output), "--quiet"]) == 2
    assert f"the output folder {output} is a file, not a folder" in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize("kind", ["symlink", "hardlink", "foreign file"])
def test_a_lock_that_is_a_link_or_another_file_is_refused_and_nothing_is_truncated(tmp_path: Path, kind: str) -> None:
    folder, other = tmp_path / "run", tmp_path / "precious.txt"
    folder.mkdir()
    other.write_text("the user's own words\n" * 4)
    lock = folder / ".lock"
    if kind == "symlink":
        lock.symlink_to(other)
    elif kind == "hardlink":
        os.link(other, lock)
    else:
        lock.write_text(other.read_text())
    with pytest.raises(UserError, match=rf"{lock} is (a symbolic link|not a lock file).*remove it"):
        with RunLock(folder):
            pass
    assert other.read_text() == "the user's own words\n" * 4
    assert lock.is_symlink() or lock.read_text() == other.read_text()


def test_resume_through_a_symlinked_lock_exits_2_and_leaves_the_target_whole(
    replica_seq: Path, tmp_path: Path, capsys
) -> None:
    out, other = tmp_path / "out", tmp_path / "precious.txt"
    assert (
        main(["run", str(replica_seq), "--output", str(out), "--name", "r", "--quiet", "--set", "dataset.end=2"]) == 0
    )
    other.write_text("keep me\n")
    (out / "r" / ".lock").unlink()
    (out / "r" / ".lock").symlink_to(other)
    assert main(["run", "--resume", str(out / "r"), "--quiet"]) == 2
    assert "is a symbolic link, not a lock file" in capsys.readouterr().err.strip().splitlines()[-1]
    assert other.read_text() == "keep me\n"


def test_overwrite_never_touches_a_folder_that_is_not_a_run_folder(tum_seq: Path, tmp_path: Path, capsys) -> None:
    dataset = tmp_path / "datasets" / "fr1_x"
    shutil.copytree(tum_seq, dataset)
    before = {p: p.read_bytes() for p in dataset.rglob("*") if p.is_file()}
    argv = ["run", str(tum_seq), "--output", str(dataset.parent), "--name", "fr1_x", "--overwrite", "--quiet"]
    assert main(argv) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"{dataset} holds groundtruth.txt but is not a run folder of gsplatam" in line
    assert {p: p.read_bytes() for p in dataset.rglob("*") if p.is_file() and p.name != ".lock"} == before


def test_overwrite_acts_on_a_run_folder_from_before_the_marker(tmp_path: Path) -> None:
    folder = tmp_path / "old"
    folder.mkdir()
    for name in ("config.toml", "frames.csv", "map.ply"):
        (folder / name).write_text("earlier")
    with new_run_folder(tmp_path, "room_tiny", "old", overwrite=True) as claimed:
        assert sorted(p.name for p in folder.iterdir()) == [".gsplatam-run", ".lock"]
        claimed.checkpoint.write_text("saved")
    assert RunFolder(folder).is_run()


@pytest.mark.parametrize("kind", ["file", "folder", "link elsewhere"])
def test_a_latest_of_the_users_is_never_replaced(tmp_path: Path, kind: str, caplog: pytest.LogCaptureFixture) -> None:
    latest = tmp_path / LATEST
    if kind == "file":
        latest.write_text("my shopping list\nmilk\n")
    elif kind == "folder":
        (latest / "inside").mkdir(parents=True)
    else:
        latest.symlink_to(tmp_path.parent)
    with new_run_folder(tmp_path, "room_tiny") as claimed:
        claimed.checkpoint.write_text("saved")
    assert claimed.path.is_dir()  # the run went on
    if kind == "file":
        assert latest.read_text() == "my shopping list\nmilk\n"
    elif kind == "folder":
        assert (latest / "inside").is_dir() and not latest.is_symlink()
    else:
        assert latest.resolve() == tmp_path.parent.resolve()
    assert f"{latest} is not gsplatam's pointer to the newest run" in caplog.text


def test_a_run_that_saved_nothing_leaves_no_folder_and_latest_where_it_was(tmp_path: Path) -> None:
    with new_run_folder(tmp_path, "room_tiny") as claimed:
        claimed.checkpoint.write_text("saved")
    earlier = (tmp_path / LATEST).resolve()
    with pytest.raises(UserError, match="no frame"):
        with new_run_folder(tmp_path, "room_tiny") as failed:
            failed.config.write_text("x")
            failed.frames_csv.write_text("index\n")
            raise UserError("no frame was processed")
    assert not failed.path.exists() and (tmp_path / LATEST).resolve() == earlier
    named = tmp_path / "mine"
    named.mkdir()
    (named / "notes.txt").write_text("mine")
    with new_run_folder(tmp_path, "room_tiny", "mine") as claimed:
        claimed.config.write_text("x")
    assert sorted(p.name for p in named.iterdir()) == ["notes.txt"]  # only what the run wrote went


def test_a_run_whose_first_frame_fails_removes_its_folder(replica_seq: Path, tmp_path: Path, capsys) -> None:
    dataset = tmp_path / "room"
    shutil.copytree(replica_seq, dataset)
    (dataset / "results" / "frame000000.jpg").write_bytes(b"truncated")
    out = tmp_path / "out"
    assert main(["run", str(dataset), "--output", str(out), "--name", "r", "--quiet"]) == 2
    assert "frame000000.jpg" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (out / "r").exists() and not (out / LATEST).exists()


def test_overwrite_follows_no_link_out_of_the_run_folder(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "rgb").mkdir(parents=True)
    (elsewhere / "rgb" / "000000.png").write_text("a user's image")
    (elsewhere / "rgb.txt").write_text("a user's listing")
    folder = tmp_path / "out" / "mine"
    (folder / "recording").mkdir(parents=True)
    (folder / "recording" / "rgb").symlink_to(elsewhere / "rgb")
    (folder / "nerfstudio").symlink_to(elsewhere)
    (folder / "map.ply").symlink_to(elsewhere / "rgb.txt")
    RunFolder(folder).mark()
    with new_run_folder(tmp_path / "out", "room_tiny", "mine", overwrite=True):
        pass
    assert (elsewhere / "rgb" / "000000.png").read_text() == "a user's image"
    assert (elsewhere / "rgb.txt").read_text() == "a user's listing"
    assert not (folder / "nerfstudio").exists() and not (folder / "map.ply").is_symlink()


def test_frames_csv_is_never_appended_through_a_link(tmp_path: Path) -> None:
    from pipeline.io.outputs.frame_row import FrameRow

    other = tmp_path / "other.txt"
    other.write_text("mine\n")
    folder = RunFolder(tmp_path)
    folder.frames_csv.symlink_to(other)
    with pytest.raises(OSError):
        folder.append_frame(FrameRow(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0, 0.0, "", "", False, 0, None, None))
    assert other.read_text() == "mine\n"
