"""The rerun sink and replay, read back from the `.rrd` files they write with rerun's own reader."""

from __future__ import annotations

import csv
import threading
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from pipeline.app.cli import main
from pipeline.config import DatasetConfig
from pipeline.frame import DeviceFrame
from pipeline.io.files.trajectory import read_tum_trajectory, write_tum_trajectory
from pipeline.io.outputs.intrinsics import CameraIntrinsics, read_intrinsics, write_intrinsics
from pipeline.io.outputs.ply import read_ply, write_ply
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.render import Gaussians
from pipeline.slam.handoff import FrameResult
from pipeline.ui import rerun_feed, rerun_recording
from pipeline.ui.rerun_feed import RerunFeed
from pipeline.ui.rerun_recording import MapSplats, RerunRecording

Rows = dict[str, list[dict[str, Any]]]


def _rows(path: Path) -> Rows:
    """Entity path -> its rows ({column: value}), in the order of the timeline `frame` (static first)."""
    from rerun.chunk import RrdReader

    rows: Rows = defaultdict(list)
    for chunk in RrdReader(path).stream():
        rows[chunk.entity_path].extend(chunk.to_record_batch().to_pylist())
    for entity in rows.values():
        entity.sort(key=lambda row: row.get("frame", -1))
    return rows


def _frames(rows: Rows, entity: str) -> list[int]:
    return [row["frame"] for row in rows[entity]]


def _pose(row: dict[str, Any]) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, :3] = np.reshape(row["Transform3D:mat3x3"][0], (3, 3)).T  # rerun's matrices are column-major
    c2w[:3, 3] = row["Transform3D:translation"][0]
    return c2w


def _path(rows: Rows, name: str) -> np.ndarray:
    """A trajectory's points from the newest strip of each of its pieces (each piece repeats the
    next one's first point)."""
    pieces = sorted((int(entity.rsplit("/", 1)[1]), entity) for entity in rows if entity.startswith(f"/world/{name}/"))
    strips = [np.array(rows[entity][-1]["LineStrips3D:strips"][0]) for _, entity in pieces]
    return np.concatenate([strips[0]] + [strip[1:] for strip in strips[1:]])


def _rgba(packed: list[int]) -> np.ndarray:
    """rerun's colours, 0xRRGGBBAA -> [N, 4] uint8."""
    rgba = np.asarray(packed, dtype=np.uint32)
    return np.stack([(rgba >> shift) & 255 for shift in (24, 16, 8, 0)], axis=1).astype(np.uint8)


def _assert_splats(row: dict[str, Any], gaussians: Gaussians) -> None:
    """A logged map row holds `gaussians` as rerun's splats: centres, scales, rotations, colours, opacities."""
    as_u8 = lambda t: (t.clamp(0, 1) * 255).to(torch.uint8).numpy()  # noqa: E731
    assert np.allclose(row["GaussianSplats3D:centers"], gaussians.means.numpy(), atol=1e-6)
    assert np.allclose(row["GaussianSplats3D:scales"], gaussians.scales().numpy(), rtol=1e-5)
    rotations = torch.nn.functional.normalize(gaussians.quats, dim=-1)[:, [1, 2, 3, 0]].numpy()
    assert np.allclose(row["GaussianSplats3D:quaternions"], rotations, atol=1e-6)
    rgba = _rgba(row["GaussianSplats3D:colors"])
    assert np.array_equal(rgba[:, :3], as_u8(gaussians.colors))
    assert np.array_equal(rgba[:, 3], as_u8(torch.sigmoid(gaussians.opacity_logits)))


@pytest.mark.slow
def test_a_run_records_every_frame_its_camera_the_trajectory_and_the_map(replica_seq: Path, tmp_path: Path) -> None:
    rrd = tmp_path / "run.rrd"
    argv = [
        "run", str(replica_seq), "--preset", "tiny", "--output", str(tmp_path), "--name", "r", "--quiet",
        "--viewer", "rerun", "--set", f"viewer.rerun_save={rrd}", "--set", "viewer.map_every_s=0",
    ]  # fmt: skip
    assert main(argv) == 0
    assert rrd.is_file() and not list(tmp_path.glob(".*.tmp"))  # written beside, renamed when complete
    rows, folder = _rows(rrd), tmp_path / "r"
    poses = read_tum_trajectory(folder / "trajectory.txt")[1]
    assert len(poses) == 6 and _frames(rows, "/world/camera") == list(range(6))
    for row, c2w in zip(rows["/world/camera"], poses):
        assert np.allclose(_pose(row), c2w, atol=1e-6)  # trajectory.txt's 9 decimals against float32
    assert np.allclose(_path(rows, "trajectory"), poses[:, :3, 3], atol=1e-6)

    camera = read_intrinsics(folder / "intrinsics.json")  # 64 pixels wide: the thumbnails are the frames
    assert _frames(rows, "/world/camera/image") == list(range(6))
    for row in rows["/world/camera/image"]:
        assert np.allclose(np.reshape(row["Pinhole:image_from_camera"][0], (3, 3)).T, camera.matrix())
        assert row["Pinhole:resolution"][0] == [64, 48]
    frames = list(open_dataset(DatasetConfig(path=str(replica_seq))).frames())
    assert _frames(rows, "/world/camera/image/color") == _frames(rows, "/world/camera/image/depth") == list(range(6))
    for frame, color, depth in zip(frames, rows["/world/camera/image/color"], rows["/world/camera/image/depth"]):
        quality = [cv2.IMWRITE_JPEG_QUALITY, rerun_recording.JPEG_QUALITY]
        expected = cv2.imencode(".jpg", cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR), quality)[1]
        assert bytes(color["EncodedImage:blob"][0]) == expected.tobytes()  # the frame's own pixels, as JPEG
        millimetres = np.frombuffer(bytes(depth["DepthImage:buffer"][0]), dtype=np.uint16).reshape(48, 64)
        assert np.abs(millimetres / 1000.0 - frame.depth).max() <= 0.0005 + 1e-6

    with open(folder / "frames.csv", newline="") as table:
        gaussians_at = {int(row["index"]): int(row["gaussians"]) for row in csv.DictReader(table)}
    snapshots = rows["/world/map"]
    assert snapshots[0]["frame"] == 0 and snapshots[-1]["frame"] == 5  # the first frame's and the final map
    for snapshot in snapshots:
        assert len(snapshot["GaussianSplats3D:centers"]) == gaussians_at[snapshot["frame"]]
    final = read_ply(folder / "map.ply")
    assert np.allclose(snapshots[-1]["GaussianSplats3D:centers"], final.means.numpy(), atol=1e-6)
    assert "run finished" in rows["/summary"][0]["TextDocument:text"][0]


class FakeSlam:
    """The members of SLAM's view the feed reads: the latest map and the poses so far."""

    def __init__(self, gaussians: Gaussians, poses: int) -> None:
        self.gaussians = gaussians
        self.poses = [_c2w(i) for i in range(poses)]


def _c2w(i: int) -> torch.Tensor:
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.1 * i, 0.0, 0.02 * i * i])
    return c2w


def _frame(index: int) -> DeviceFrame:
    k = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    color = torch.full((12, 16, 3), index / 10)
    return DeviceFrame(index, 0.0, color, torch.full((12, 16), 1.0 + index / 10), k, None)


def _result(index: int) -> FrameResult:
    seconds = {"tracking": 0.01, "densify": 0.0, "mapping": 0.02, "total": 0.03}
    return FrameResult(index, 0.0, _c2w(index), seconds, 10, 0, 0.0, 1.0)


def _gaussians(n: int) -> Gaussians:
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return Gaussians(torch.rand(n, 3), quats, torch.full((n, 1), -3.0), torch.zeros(n), torch.rand(n, 3))


def test_a_logger_behind_skips_images_never_poses_and_maps_are_copied_at_the_boundary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(rerun_feed, "QUEUE_FRAMES", 2)
    rrd = tmp_path / "feed.rrd"
    recording = RerunRecording("test", rrd)
    entered, gate = threading.Event(), threading.Event()
    pose = recording.pose

    def held_pose(c2w: np.ndarray) -> None:  # the logger, held at its first pose until `gate`
        entered.set()
        gate.wait(10)
        pose(c2w)

    monkeypatch.setattr(recording, "pose", held_pose)
    feed = RerunFeed(recording, map_every_s=1e9, device=torch.device("cpu"))
    slam = FakeSlam(_gaussians(10), poses=4)  # resumed after 3 frames: frame 3 is the first this run
    first_map = slam.gaussians.means.clone()
    feed(slam, _frame(3), _result(3))  # the logger takes it (and the map, due at the start), then waits
    assert entered.wait(10)
    slam.gaussians.means.add_(1.0)  # SLAM moves on: the snapshot must not change
    for index in range(4, 8):  # 4 and 5 wait in the queue; 6 and 7 find it full
        slam.poses.append(_c2w(index))
        feed(slam, _frame(index), _result(index))
    assert feed.skipped == 2
    gate.set()
    feed.finish()
    assert not rrd.exists()  # until the recording is complete
    feed.close()
    feed.close()  # safe twice
    assert rrd.is_file() and not list(tmp_path.glob(".*.tmp"))

    rows = _rows(rrd)
    assert _frames(rows, "/world/camera") == list(range(8))  # every pose, the resumed ones too
    for row, number in zip(rows["/world/camera"], range(8)):
        assert np.allclose(_pose(row), _c2w(number).numpy())
    assert np.allclose(_path(rows, "trajectory"), torch.stack([_c2w(i) for i in range(8)])[:, :3, 3].numpy())
    assert _frames(rows, "/world/camera/image/color") == [3, 4, 5]
    assert _frames(rows, "/world/map") == [3, 7]  # the first, then the final one at the end
    first, final = (np.array(row["GaussianSplats3D:centers"]) for row in rows["/world/map"])
    assert np.allclose(first, first_map.numpy()) and np.allclose(final, slam.gaussians.means.numpy())


def test_long_trajectories_are_pieces_and_only_the_pieces_with_new_poses_are_logged_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(rerun_recording, "TRAJECTORY_PIECE", 4)
    centres = np.random.default_rng(0).normal(size=(10, 3))
    recording = RerunRecording("test", tmp_path / "t.rrd")
    for since in range(0, 10, 3):
        recording.at(since)
        recording.trajectory("trajectory", centres[: since + 3], since=since)
    recording.close()
    rows = _rows(tmp_path / "t.rrd")
    assert np.allclose(_path(rows, "trajectory"), centres)
    # pieces [0..4], [4..8], [8..9]: new centres 0-2, 3-5, 6-8, 9 touch pieces {0}, {0, 1}, {1, 2}, {2}
    assert [_frames(rows, f"/world/trajectory/{k}") for k in range(3)] == [[0, 3], [3, 6], [6, 9]]


def _run_folder(folder: Path) -> tuple[Gaussians, np.ndarray, np.ndarray, CameraIntrinsics]:
    folder.mkdir()
    gaussians = _gaussians(25)
    write_ply(folder / "map.ply", gaussians)
    poses = torch.stack([_c2w(i) for i in range(5)]).double().numpy()
    reference = poses.copy()
    reference[:, 1, 3] += 0.05
    write_tum_trajectory(folder / "trajectory.txt", np.arange(5.0), poses)
    write_tum_trajectory(folder / "groundtruth.txt", np.arange(5.0), reference)
    camera = CameraIntrinsics(50.0, 51.0, 31.5, 24.0, 64, 48)
    write_intrinsics(folder / "intrinsics.json", camera)
    return gaussians, poses, reference, camera


def test_view_replays_a_run_folder_to_a_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gaussians, poses, reference, camera = _run_folder(tmp_path / "run")
    rrd = tmp_path / "replay.rrd"
    assert main(["view", str(tmp_path / "run"), "--rerun-save", str(rrd)]) == 0
    assert f"wrote {rrd}: 25 Gaussians" in capsys.readouterr().out
    rows = _rows(rrd)
    saved = read_ply(tmp_path / "run" / "map.ply")
    (splats,) = rows["/world/map"]
    _assert_splats(splats, saved)
    assert _frames(rows, "/world/camera") == list(range(5))
    assert all(np.allclose(_pose(row), c2w, atol=1e-6) for row, c2w in zip(rows["/world/camera"], poses))
    (pinhole,) = rows["/world/camera/image"]
    assert np.allclose(np.reshape(pinhole["Pinhole:image_from_camera"][0], (3, 3)).T, camera.matrix())
    assert pinhole["Pinhole:resolution"][0] == [64, 48]
    assert np.allclose(_path(rows, "trajectory"), poses[:, :3, 3], atol=1e-6)
    assert np.allclose(_path(rows, "groundtruth"), reference[:, :3, 3], atol=1e-6)

    assert main(["view", str(tmp_path / "run" / "map.ply"), "--rerun-save", str(tmp_path / "map.rrd")]) == 0
    alone = _rows(tmp_path / "map.rrd")
    assert "/world/map" in alone and "/world/camera" not in alone  # a PLY alone: the map only


def test_rerun_mistakes_are_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _run_folder(tmp_path / "run")
    assert main(["view", str(tmp_path / "run"), "--rerun-save", str(tmp_path / "absent" / "x.rrd")]) == 2
    assert "cannot write the rerun recording" in capsys.readouterr().err
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(rerun_recording.sys, "platform", "linux")
    assert main(["view", str(tmp_path / "run"), "--rerun"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gsplatam: error: rerun's viewer needs a display")
    assert "--rerun-save FILE.rrd" in err[0] and not list(tmp_path.glob("**/*.rrd*"))


def test_the_map_is_logged_as_gaussian_splats_and_as_points_where_rerun_lacks_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    gaussians = _gaussians(7)
    gaussians.log_scales = torch.randn(7, 3) - 3  # anisotropic
    gaussians.quats = torch.randn(7, 4)  # unnormalised, as SLAM holds them
    gaussians.opacity_logits = torch.randn(7)
    recording = RerunRecording("test", tmp_path / "splats.rrd")
    recording.map(MapSplats.of(gaussians), static=True)
    recording.close()
    (row,) = _rows(tmp_path / "splats.rrd")["/world/map"]
    _assert_splats(row, gaussians)

    monkeypatch.setattr(rerun_recording, "SPLATS", False)
    recording = RerunRecording("test", tmp_path / "points.rrd")
    recording.map(MapSplats.of(gaussians), static=True)
    recording.close()
    (row,) = _rows(tmp_path / "points.rrd")["/world/map"]
    assert np.allclose(row["Points3D:positions"], gaussians.means.numpy(), atol=1e-6)
    assert np.array_equal(_rgba(row["Points3D:colors"])[:, :3], (gaussians.colors * 255).to(torch.uint8).numpy())
