"""The nerfstudio export read as nerfstudio's `nerfstudio-data` parser reads it
(nerfstudio/data/dataparsers/nerfstudio_dataparser.py): its fields, OpenGL camera axes, file
paths, split lists and depth in millimetres; every frame or the keyframes; working or native size."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch
from conftest import GT_KEYFRAMES, GT_ROOM, write_gt_run

from pipeline.app.cli import main
from pipeline.config import load_config
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.intrinsics import write_intrinsics
from pipeline.io.outputs.run_folder import RunFolder

WORKING = (32, 24)  # the run's working size; the room is stored at 64x48


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run of the room whose working size is half its stored size, as such a run leaves it:
    keyframes and intrinsics.json at the working size."""
    run = write_gt_run(tmp_path_factory.mktemp("ns"))
    folder = RunFolder(run)
    config = folder.read_config()
    folder.write_config(replace(config, dataset=replace(config.dataset, width=WORKING[0], height=WORKING[1])))
    checkpoint, description = folder.read_checkpoint()
    keyframes = [
        replace(
            k,
            color_u8=torch.from_numpy(cv2.resize(k.color_u8.numpy(), WORKING, interpolation=cv2.INTER_AREA)),
            depth=torch.from_numpy(cv2.resize(k.depth.numpy(), WORKING, interpolation=cv2.INTER_NEAREST)),
        )
        for k in checkpoint.keyframes
    ]
    halved = replace(checkpoint, mapping=replace(checkpoint.mapping, keyframes=keyframes))
    folder.write_state(halved, description, read_tum_trajectory(folder.trajectory)[0], None)
    camera = folder.read_intrinsics()
    write_intrinsics(
        folder.intrinsics, replace(camera, fx=camera.fx / 2, fy=camera.fy / 2, cx=camera.cx / 2, cy=camera.cy / 2,
                                   width=WORKING[0], height=WORKING[1]),
    )  # fmt: skip
    return run


def parse_like_nerfstudio(folder: Path) -> dict[str, Any]:
    """What nerfstudio's parser checks and derives: camera fields, frames sorted by file name,
    every file present, as many depth files as images, the three split lists (all or none) each
    naming images of the frames -> {images, depths, poses [N, 4, 4], splits, camera}."""
    meta = json.loads((folder / "transforms.json").read_text())
    camera = {key: meta[key] for key in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
    assert meta["camera_model"] in ("OPENCV", "PINHOLE")
    frames = sorted(meta["frames"], key=lambda f: f["file_path"])
    images = [folder / f["file_path"] for f in frames]
    depths = [folder / f["depth_file_path"] for f in frames]
    assert all(p.is_file() for p in images + depths) and (folder / meta["ply_file_path"]).is_file()
    splits = {name: [folder / f for f in meta[f"{name}_filenames"]] for name in ("train", "val", "test")}
    assert all(set(files) <= set(images) and files for files in splits.values())
    poses = np.array([f["transform_matrix"] for f in frames])
    assert poses.shape == (len(frames), 4, 4) and np.allclose(poses[:, 3], [0, 0, 0, 1])
    for image, depth in zip(images, depths):
        assert cv2.imread(str(image)).shape[:2] == (camera["h"], camera["w"])
        assert cv2.imread(str(depth), cv2.IMREAD_UNCHANGED).shape == (camera["h"], camera["w"])
    return {"images": images, "depths": depths, "poses": poses, "splits": splits, "camera": camera}


def _export(run: Path, out: Path, *options: str) -> dict[str, Any]:
    assert main(["export", str(run), "--to", "nerfstudio", "--output", str(out), *options]) == 0
    return parse_like_nerfstudio(out)


def test_keyframes_at_the_working_size_hold_out_one_of_three_for_evaluation(run: Path, tmp_path: Path) -> None:
    parsed = _export(run, tmp_path / "ns")
    names = [p.name for p in parsed["images"]]
    assert names == [f"frame_{i:06d}.png" for i in GT_KEYFRAMES]
    assert len(parsed["splits"]["train"]) == 2 and len(parsed["splits"]["val"]) == 1
    assert set(parsed["splits"]["train"]).isdisjoint(parsed["splits"]["val"])


def test_every_frame_at_the_working_size_with_the_runs_poses(run: Path, tmp_path: Path) -> None:
    parsed = _export(run, tmp_path / "all", "--frames", "all")
    assert len(parsed["images"]) == GT_ROOM.frames
    assert (parsed["camera"]["w"], parsed["camera"]["h"]) == WORKING
    poses = RunFolder(run).read_checkpoint()[0].poses.double().numpy()
    opencv = parsed["poses"] @ np.diag([1.0, -1.0, -1.0, 1.0])  # nerfstudio's OpenGL axes -> OpenCV
    assert np.allclose(opencv, poses, atol=1e-6)


def test_native_size_has_the_datasets_images_and_the_working_intrinsics_scaled(run: Path, tmp_path: Path) -> None:
    native = _export(run, tmp_path / "native", "--frames", "all", "--size", "native")
    working = _export(run, tmp_path / "working", "--frames", "all")
    assert (native["camera"]["w"], native["camera"]["h"]) == (GT_ROOM.width, GT_ROOM.height)
    scale = GT_ROOM.width / WORKING[0]
    for key in ("fl_x", "fl_y", "cx", "cy"):
        assert native["camera"][key] == pytest.approx(working["camera"][key] * scale, rel=1e-6), key
    room = Path(load_config(config_file=RunFolder(run).config).dataset.path)
    stored = sorted((room / "results").glob("frame*.jpg"))[0]
    assert np.abs(cv2.imread(str(native["images"][0])).astype(int) - cv2.imread(str(stored)).astype(int)).max() <= 1


def test_frames_and_size_are_refused_for_other_formats(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(run), "--to", "splat", "--frames", "all"]) == 2
    assert "apply to --to nerfstudio only" in capsys.readouterr().err


def test_nerfstudios_own_dataparser_reads_the_export(run: Path, tmp_path: Path) -> None:
    dataparser = pytest.importorskip(
        "nerfstudio.data.dataparsers.nerfstudio_dataparser",
        reason="nerfstudio is not installed (it pins its own torch and dependencies; pip install nerfstudio)",
    )
    out = tmp_path / "ns"
    assert main(["export", str(run), "--to", "nerfstudio", "--output", str(out), "--frames", "all"]) == 0
    config = dataparser.NerfstudioDataParserConfig(data=out, downscale_factor=1)
    train = config.setup().get_dataparser_outputs("train")
    val = config.setup().get_dataparser_outputs("val")
    assert len(train.image_filenames) + len(val.image_filenames) == GT_ROOM.frames
    assert len(train.metadata["depth_filenames"]) == len(train.image_filenames)
