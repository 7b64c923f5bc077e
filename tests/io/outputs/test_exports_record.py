"""exports.json: which map each export came from; marked stale when the map moves on, removed
by --overwrite, and kept out of the list of what a run wrote."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import make_checkpoint, write_gt_run

from pipeline.app.cli import main
from pipeline.app.report import files_and_next_steps
from pipeline.io.outputs.frame_row import COLUMNS
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.slam.gaussian_map import concatenate


@pytest.fixture(scope="module")
def gt_run_once(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_gt_run(tmp_path_factory.mktemp("record"))


@pytest.fixture
def run(gt_run_once: Path, tmp_path: Path) -> RunFolder:
    shutil.copytree(gt_run_once, tmp_path / "run")
    folder = RunFolder(tmp_path / "run")
    row = {name: "0" for name in COLUMNS}
    lines = [",".join(COLUMNS)] + [
        ",".join({**row, "index": str(i), "map_version": str(2 * i)}.values()) for i in range(6)
    ]
    folder.frames_csv.write_text("\n".join(lines) + "\n")
    return folder


def _resumed(folder: RunFolder) -> None:
    """What a resumed run's save does: trajectory, map and checkpoint of a longer run."""
    checkpoint, run = folder.read_checkpoint()
    grown = concatenate(checkpoint.gaussians, checkpoint.gaussians)
    poses = np.concatenate([checkpoint.poses.numpy()] * 2)
    longer = make_checkpoint(grown, checkpoint.keyframes, checkpoint.poses.new_tensor(poses))
    folder.write_state(longer, RunDescription("room"), np.arange(len(poses), dtype=float), None)


def test_an_export_records_the_map_it_came_from(run: RunFolder, tmp_path: Path) -> None:
    assert main(["export", str(run.path), "--to", "splat"]) == 0
    assert main(["export", str(run.path), "--to", "pointcloud", "--output", str(tmp_path / "pc.ply")]) == 0
    checkpoint, _ = run.read_checkpoint()
    record = json.loads(run.exports_record.read_text())
    assert record["splat"] == {
        "path": "map.splat", "frames": 6, "frames_mapped": 6, "gaussians": len(checkpoint.gaussians), "map_version": 10
    }  # fmt: skip
    assert record["pointcloud"]["path"] == str(tmp_path / "pc.ply")


def test_a_resumed_run_marks_earlier_exports_stale_and_lists_them_apart(run: RunFolder) -> None:
    assert main(["export", str(run.path), "--to", "splat"]) == 0
    _resumed(run)
    assert json.loads(run.exports_record.read_text())["splat"]["stale"] == "made from 6 frames; the map now holds 12"
    printed = files_and_next_steps(run)
    outputs = printed.split("exports made before this run")[0]
    assert "map.splat" not in outputs and "exports.json" not in outputs and "  map.ply" in outputs
    assert "  map.splat: made from 6 frames; the map now holds 12" in printed


def test_overwrite_removes_the_exports_it_recorded_inside_the_folder(run: RunFolder, tmp_path: Path) -> None:
    inside, outside = run.path / "mine.splat", tmp_path / "elsewhere.splat"
    assert main(["export", str(run.path), "--to", "splat", "--output", str(inside)]) == 0
    assert main(["export", str(run.path), "--to", "ply", "--output", str(outside)]) == 0
    run.remove_earlier_run()
    assert not inside.exists() and not run.exports_record.exists() and outside.exists()
