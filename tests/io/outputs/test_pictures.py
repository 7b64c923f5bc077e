"""Pictures of a run: renders beside the input, the trajectory plot, the fly-through video."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import GT_ROOM, write_gt_run

from pipeline.app.cli import main
from pipeline.io.outputs.pictures import render_picture, spread, trajectory_png
from pipeline.io.outputs.run_folder import RunFolder


def test_spread_picks_evenly_from_the_first_to_the_last() -> None:
    assert spread(list(range(0, 100, 5)), 3) == [0, 50, 95]
    assert spread([0, 5, 10], 20) == [0, 5, 10] and spread([0, 5], 0) == [] and spread([7, 9], 1) == [7]


def test_a_render_picture_puts_the_input_beside_its_render_on_one_depth_scale() -> None:
    color = np.zeros((48, 64, 3))
    color[..., 0] = 1.0
    depth = np.full((48, 64), 2.0)
    depth[:, :8] = 0  # no depth: black
    rendered = np.zeros((48, 64, 3))
    picture = render_picture(color, depth, rendered, depth * 0.5)
    assert picture.shape == (96, 128, 3) and picture.dtype == np.uint8
    assert (picture[10, 10] == [255, 0, 0]).all() and (picture[10, 64 + 10] == 0).all()
    assert (picture[48 + 10, 2] == 0).all()  # no depth
    assert not (picture[48 + 10, 20] == picture[48 + 10, 64 + 20]).all()  # 2 m and 1 m differ in colour
    big = render_picture(np.zeros((680, 1200, 3)), np.ones((680, 1200)), np.zeros((680, 1200, 3)), np.ones((680, 1200)))
    assert big.shape[1] <= 1280  # halved: a picture stays small


def test_the_trajectory_plot_is_a_png() -> None:
    t = np.arange(20) / 30.0
    poses = np.repeat(np.eye(4)[None], 20, axis=0)
    poses[:, 0, 3] = np.linspace(0, 1, 20)
    image = cv2.imdecode(np.frombuffer(trajectory_png(t, poses, poses.copy()), np.uint8), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    assert cv2.imdecode(np.frombuffer(trajectory_png(t, poses, None), np.uint8), cv2.IMREAD_COLOR) is not None


def test_overwrite_removes_a_runs_pictures_and_nothing_else(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path)
    folder.renders.mkdir()
    (folder.renders / "frame000000.png").write_bytes(b"x")
    (folder.renders / "notes.txt").write_text("mine")
    folder.trajectory_plot.write_bytes(b"x")
    folder.remove_earlier_run()
    assert not folder.trajectory_plot.exists() and [p.name for p in folder.renders.iterdir()] == ["notes.txt"]


@pytest.fixture(scope="module")
def gt_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_gt_run(tmp_path_factory.mktemp("pictures"))


def test_render_video_flies_along_the_trajectory(gt_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import av

    assert main(["render", str(gt_run), "--video", "--fps", "10"]) == 0
    video = gt_run / "flythrough.mp4"
    assert f"wrote {video}: {GT_ROOM.frames} frames at 10 frames/s" in capsys.readouterr().out
    with av.open(str(video)) as container:
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    assert len(frames) == GT_ROOM.frames and frames[0].shape == (GT_ROOM.height, GT_ROOM.width, 3)
    assert float(np.mean(frames[0])) > 10  # the map, not a black screen
    record = json.loads((gt_run / "exports.json").read_text())
    assert record["video"]["path"] == "flythrough.mp4" and record["video"]["frames"] == GT_ROOM.frames


@pytest.mark.parametrize(
    "options, message",
    [
        ([], "say what to render: --video"),
        (["--video", "--fps", "0"], "--fps must be > 0 and at most 240, not 0.0"),
        (["--video", "--stride", "0"], "--stride must be >= 1"),
        (["--video", "--back", "nan"], "--back must be 0 to 100 metres"),
        (["--video", "--output", "{run}/map.ply"], "is one of the run folder"),
        (["--video", "--output", "{run}"], "is a folder: --output names the .mp4 file to write"),
    ],
)
def test_render_refuses_what_it_cannot_do_in_one_line(
    gt_run: Path, options: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    before = (gt_run / "map.ply").read_bytes()
    assert main(["render", str(gt_run), *[o.format(run=gt_run) for o in options]]) == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]
    assert (gt_run / "map.ply").read_bytes() == before
