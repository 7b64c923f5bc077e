"""Run folders received from someone else, or changed behind a run's back: links planted in
them, an exports.json that is not sound, exports made at once, a dataset changed since the run,
temporary names of the user's, a refused --overwrite. Nothing outside the run folder is touched,
every refusal is one line and writes nothing."""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import GT_ROOM, checkpoint_with_loops, write_gt_run
from safetensors import safe_open
from safetensors.torch import save_file

from pipeline.app.cli import main
from pipeline.errors import UserError
from pipeline.io.outputs.checkpoint import write_checkpoint
from pipeline.io.outputs.exports_record import ExportsRecord
from pipeline.io.outputs.frame_row import FrameRow
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_folders import new_run_folder
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.slam.gaussian_map import concatenate


@pytest.fixture(scope="module")
def gt_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A run of the room in each layout (a map from its exact depth), with its frames.csv."""
    runs = {}
    for layout in ("replica", "tum"):
        root = tmp_path_factory.mktemp(layout)
        run = write_gt_run(root, replace(GT_ROOM, layout=layout))
        folder = RunFolder(run)
        for ref in open_dataset(folder.read_config().dataset).refs:
            folder.append_frame(FrameRow(ref.index, ref.timestamp, 0, 0, 0, 0, 1, 1, 0, 1, "", "", True, 1, None, None))
        folder.close()
        folder.mark()
        runs[layout] = root
    return runs


def _copy(gt_runs: dict[str, Path], tmp_path: Path, layout: str = "replica") -> RunFolder:
    """A copy of the run (and its dataset, which the copy's config names)."""
    shutil.copytree(gt_runs[layout], tmp_path / "copy")
    folder = RunFolder(tmp_path / "copy" / "run")
    config = folder.read_config()
    folder.write_config(replace(config, dataset=replace(config.dataset, path=str(tmp_path / "copy" / "room"))))
    return folder


def _overwrite(folder: RunFolder) -> None:
    with new_run_folder(folder.path.parent, "room", folder.path.name, overwrite=True):
        pass


def _outside(tmp_path: Path) -> Path:
    """A folder outside the run folder holding the user's files, which nothing may touch."""
    outside = tmp_path / "outside"
    (outside / "images").mkdir(parents=True)
    for name in ("victim.txt", "transforms.json", "images/frame_000000.png"):
        (outside / name).write_text("the user's")
    return outside


def _untouched(outside: Path) -> bool:
    return all((outside / name).read_text() == "the user's" for name in ("victim.txt", "transforms.json"))


@pytest.mark.parametrize("entry", [("splat", "lnk/victim.txt"), ("nerfstudio", "lnk"), ("nerfstudio", "sub/lnk")])
def test_overwrite_never_follows_a_recorded_path_through_a_link(
    gt_runs: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture, entry: tuple[str, str]
) -> None:
    """exports.json names a file through a linked folder, or a nerfstudio export that is a link
    (or lies beyond one): --overwrite removes the link at most, never what lies behind it."""
    folder, outside = _copy(gt_runs, tmp_path), _outside(tmp_path)
    (folder.path / "lnk").symlink_to(outside, target_is_directory=True)
    (folder.path / "sub").mkdir()
    (folder.path / "sub" / "lnk").symlink_to(outside, target_is_directory=True)
    fmt, path = entry
    folder.exports_record.write_text(json.dumps({fmt: {"path": path, "frames": 6, "gaussians": 1}}))
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        _overwrite(folder)
    assert _untouched(outside) and (outside / "images" / "frame_000000.png").exists()
    if path == "lnk/victim.txt":
        assert "leads out of" in caplog.text and (folder.path / "lnk").is_symlink()
    assert not folder.checkpoint.exists() and not folder.exports_record.exists()


def test_a_nerfstudio_export_over_a_link_replaces_the_link_only(gt_runs: dict[str, Path], tmp_path: Path) -> None:
    folder, outside = _copy(gt_runs, tmp_path), _outside(tmp_path)
    (outside / "victim.txt").unlink()  # an earlier nerfstudio export, elsewhere
    folder.export("nerfstudio").symlink_to(outside, target_is_directory=True)
    assert main(["export", str(folder.path), "--to", "nerfstudio"]) == 0
    assert folder.export("nerfstudio").is_dir() and not folder.export("nerfstudio").is_symlink()
    assert (outside / "transforms.json").read_text() == "the user's"
    assert [p.name for p in folder.path.iterdir() if p.name.endswith(".tmp")] == []


@pytest.mark.parametrize(
    "record",
    ['{"splat": "map.splat", "ply": 7}', "not json", '["map.splat"]', '{"splat": {"path": 3}}',
     '{"splat": {"path": "map.splat", "frames": -1}}'],
)  # fmt: skip
def test_an_unsound_exports_record_is_reported_and_rebuilt_from_the_exports_present(
    gt_runs: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture, record: str
) -> None:
    folder = _copy(gt_runs, tmp_path)
    assert main(["export", str(folder.path), "--to", "splat"]) == 0
    assert main(["export", str(folder.path), "--to", "pointcloud", "--output", str(tmp_path / "pc.ply")]) == 0
    folder.exports_record.write_text(record)
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        _resumed(folder)  # a resume's save moves the map on
    assert "exports.json" in caplog.text and "rebuilt from the exports present" in caplog.text
    rebuilt = json.loads(folder.exports_record.read_text())
    assert rebuilt["splat"]["path"] == "map.splat" and "stale" in rebuilt["splat"]
    assert "pointcloud" not in rebuilt  # elsewhere, and no longer recorded: left alone
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        _overwrite(folder)
    assert not (folder.path / "map.splat").exists() and (tmp_path / "pc.ply").exists()
    assert "Traceback" not in caplog.text


def test_an_unsound_record_is_rebuilt_by_the_next_export_too(gt_runs: dict[str, Path], tmp_path: Path) -> None:
    folder = _copy(gt_runs, tmp_path)
    assert main(["export", str(folder.path), "--to", "splat"]) == 0
    folder.exports_record.write_text('{"splat": "map.splat", "ply": 7}')
    assert main(["export", str(folder.path), "--to", "pointcloud"]) == 0
    record = json.loads(folder.exports_record.read_text())
    assert set(record) == {"splat", "pointcloud"} and "stale" in record["splat"] and "stale" not in record["pointcloud"]


def test_exports_made_at_once_each_keep_their_entry(
    gt_runs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Five exports recording at once, each read slowed so that they overlap: without the lock
    all but one entry would be lost."""
    folder = _copy(gt_runs, tmp_path)
    checkpoint, _ = folder.read_checkpoint()
    read = ExportsRecord.read

    def slow_read(self: ExportsRecord) -> tuple[dict[str, dict[str, object]], bool]:
        found = read(self)
        time.sleep(0.05)
        return found

    monkeypatch.setattr(ExportsRecord, "read", slow_read)
    formats = ["splat", "ply", "compressed-ply", "pointcloud", "mesh"]
    writers = [
        threading.Thread(target=RunFolder(folder.path).record_export, args=(fmt, folder.export(fmt), checkpoint))
        for fmt in formats
    ]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(60)
    assert sorted(json.loads(folder.exports_record.read_text())) == sorted(formats)


def test_every_frame_of_a_dataset_whose_images_were_replaced_is_refused(
    gt_runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _copy(gt_runs, tmp_path)
    for image in sorted((tmp_path / "copy" / "room" / "results").glob("*[0-9].*")):  # colour and depth
        read = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(image), cv2.resize(read, (32, 24), interpolation=cv2.INTER_NEAREST))
    for size in ("working", "native"):
        out = tmp_path / f"ns-{size}"
        assert main(["export", str(folder.path), "--to", "nerfstudio", "--frames", "all", "--size", size,
                     "--output", str(out)]) == 2  # fmt: skip
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert "are now 32x24" in line and "not the run's camera (64x48" in line and "dataset changed" in line
        assert not out.exists()


def test_every_frame_of_a_dataset_whose_lists_changed_is_refused_naming_the_first_frame(
    gt_runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two lines gone from rgb.txt: the images of frames 2-4 would be paired with the poses of
    frames 0-2; frames.csv holds the timestamps that show it."""
    folder = _copy(gt_runs, tmp_path, "tum")
    rgb = tmp_path / "copy" / "room" / "rgb.txt"
    lines = rgb.read_text().splitlines(keepends=True)
    frames = [i for i, line in enumerate(lines) if not line.startswith("#")]
    rgb.write_text("".join(line for i, line in enumerate(lines) if i not in frames[2:4]))
    before = sorted(p.name for p in folder.path.iterdir())
    assert main(["export", str(folder.path), "--to", "nerfstudio", "--frames", "all"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "frame 2 of the dataset" in line and "frames.csv has it at" in line
    assert sorted(p.name for p in folder.path.iterdir()) == before


def test_overwrite_leaves_the_users_own_temporary_names(gt_runs: dict[str, Path], tmp_path: Path) -> None:
    folder = _copy(gt_runs, tmp_path)
    (folder.path / ".mine.tmp").mkdir()
    (folder.path / ".mine.tmp" / "draft.txt").write_text("mine")
    (folder.path / ".notes.tmp").write_text("mine")
    ours = [
        ".gsplatam-map.ply.x1.tmp",
        ".map.ply.x2.tmp",
        ".gsplatam-nerfstudio.1.ab.tmp",
    ]  # the last: a version before
    for name in ours:
        (folder.path / name).write_text("a kill's leftover")
    _overwrite(folder)
    assert (folder.path / ".mine.tmp" / "draft.txt").read_text() == "mine"
    assert (folder.path / ".notes.tmp").read_text() == "mine"
    assert not any((folder.path / name).exists() for name in ours)


def test_a_refused_overwrite_of_a_dataset_folder_writes_nothing_there(
    replica_seq: Path, tum_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dataset = tmp_path / "data" / "room"
    shutil.copytree(tum_seq, dataset)
    before = {p: p.stat().st_mtime_ns for p in dataset.rglob("*")}
    code = main(["run", str(replica_seq), "--output", str(dataset.parent), "--name", "room", "--overwrite", "--quiet"])
    assert code == 2 and "is not a run folder of gsplatam" in capsys.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in dataset.rglob("*")} == before  # no .lock left behind either


def _resumed(folder: RunFolder, loops: bool = True) -> None:
    """What a resumed run's save does: trajectory, map and checkpoint of a longer run."""
    checkpoint, run = folder.read_checkpoint()
    longer = replace(
        checkpoint,
        tracking=replace(checkpoint.tracking, poses=checkpoint.poses.repeat(2, 1, 1)),
        mapping=replace(checkpoint.mapping, gaussians=concatenate(checkpoint.gaussians, checkpoint.gaussians)),
    )
    folder.write_state(longer, run, np.arange(2 * checkpoint.frames_done, dtype=float), None)


def test_a_resume_without_loop_closure_leaves_no_pose_graph_of_the_shorter_run(
    gt_runs: dict[str, Path], tmp_path: Path
) -> None:
    folder = _copy(gt_runs, tmp_path)
    folder.pose_graph.write_text("# the earlier run's graph\n")
    folder.trajectory_as_tracked.write_text("0 0 0 0 0 0 0 1\n")
    _resumed(folder)
    assert not folder.pose_graph.exists() and not folder.trajectory_as_tracked.exists()


def _header_changed(path: Path, change: dict[str, object]) -> None:
    """Rewrite the checkpoint's JSON header with the loop-closure fields in `change`."""
    with safe_open(str(path), framework="pt") as f:
        meta, tensors = f.metadata(), {key: f.get_tensor(key) for key in f.keys()}
    header = json.loads(meta["gsplatam"])
    header["loops"] = {**header["loops"], **change}
    save_file(tensors, str(path), {"gsplatam": json.dumps(header)})


@pytest.mark.parametrize(
    "change, named",
    [({"tally": {"detected": 1, "sneaky": 2}}, "'sneaky', not a count"),
     ({"tally": {"detected": -1}}, "detected is -1"),
     ({"tally": [1, 2]}, "list"),
     ({"node_positions": [0, 5, 10**6]}, "1000000"),
     ({"node_positions": [5, 0, 11]}, "in order")],
)  # fmt: skip
def test_a_tampered_loop_field_is_one_line_and_exit_2(
    gt_runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], change: dict[str, object], named: str
) -> None:
    folder = _copy(gt_runs, tmp_path)
    write_checkpoint(folder.checkpoint, checkpoint_with_loops(9), RunDescription("room"))
    _header_changed(folder.checkpoint, change)
    assert main(["export", str(folder.path), "--to", "splat"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "is not a gsplatam checkpoint" in line and named in line


def test_a_refused_run_name_raises_before_the_lock(tmp_path: Path) -> None:
    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "groundtruth.txt").write_text("# a dataset's\n")
    with pytest.raises(UserError, match="not a run folder of gsplatam"):
        with new_run_folder(tmp_path, "room", "data", overwrite=True):
            pass
    assert sorted(p.name for p in folder.iterdir()) == ["groundtruth.txt"]
