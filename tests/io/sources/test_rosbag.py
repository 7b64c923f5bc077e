"""Bags as datasets: a ROS 1 bag, a ROS 2 bag (SQLite), an MCAP file and a RealSense recording,
each written from the TUM folder, read as that folder reads; bad bags are one line and exit 2."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from bag_writers import BagWriter, TumFolder, write_realsense_bag, write_tum_bag

from pipeline.app.cli import main
from pipeline.config import DatasetConfig
from pipeline.errors import DataError
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.sources.datasets import ros_messages
from pipeline.io.sources.datasets.loader import open_dataset

TOPICS = {  # what each bag names by settings (the rest is found)
    "ros1.bag": {},
    "ros2": {},
    "file.mcap": {"pose_frames": ("world", "camera_color_optical_frame")},
    "realsense.bag": {},
}
FIRST_FRAMES = ["--set", "dataset.end=4"]  # the end-to-end runs: enough frames to track, few to keep the suite short
DEPTH_TOLERANCE_M = {"ros1.bag": 0.0005, "ros2": 0.0, "file.mcap": 0.0, "realsense.bag": 1e-6}  # 16UC1 rounds to mm


def _write(name: str, path: Path, folder: TumFolder) -> Path:
    if name == "ros1.bag":
        return write_tum_bag(path, folder, "ros1")
    if name == "ros2":
        return write_tum_bag(path, folder, "sqlite3", depth="32FC1", color="bgr8", pose="Odometry")
    if name == "file.mcap":  # the MCAP file alone, without its folder's metadata.yaml
        write_tum_bag(path.with_suffix(""), folder, "mcap", depth="32FC1", color="png", pose="tf")
        (path.with_suffix("") / "file.mcap").rename(path)
        return path
    return write_realsense_bag(path, folder)


@pytest.fixture(scope="session")
def bags(tum_seq: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root, folder = tmp_path_factory.mktemp("bags"), TumFolder.read(tum_seq)
    return {name: _write(name, root / name, folder) for name in TOPICS}


def _config(path: Path, **settings: object) -> DatasetConfig:
    return DatasetConfig(path=str(path), **settings)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", list(TOPICS))
def test_a_bag_gives_the_frames_of_the_tum_folder_it_was_written_from(
    name: str, bags: dict[str, Path], tum_seq: Path
) -> None:
    tum = open_dataset(DatasetConfig(path=str(tum_seq)))
    bag = open_dataset(_config(bags[name], **TOPICS[name]))
    assert bag.format == "rosbag" and len(bag) == len(tum) and bag.size == tum.size
    assert np.allclose(bag.intrinsics, tum.intrinsics)
    for ours, theirs in zip(bag.refs, tum.refs):
        frame, expected = bag.decode(ours), tum.decode(theirs)
        assert frame.timestamp == pytest.approx(expected.timestamp, abs=1e-6)
        assert np.array_equal(frame.color, expected.color)
        assert np.abs(frame.depth - expected.depth).max() <= DEPTH_TOLERANCE_M[name] + 1e-7
        if name == "realsense.bag":  # a RealSense recording carries no poses
            assert frame.c2w_gt is None
        else:  # the pose topic, or /tf through a static link to the optical frame
            assert frame.c2w_gt is not None and expected.c2w_gt is not None
            assert np.allclose(frame.c2w_gt, expected.c2w_gt, atol=1e-6)


def test_slicing_and_resizing_apply_to_bags_as_to_folders(bags: dict[str, Path], tum_seq: Path) -> None:
    settings = {"start": 1, "stride": 2, "width": 32, "height": 24}
    bag = open_dataset(_config(bags["ros2"], **settings))
    tum = open_dataset(_config(tum_seq, **settings))
    assert [r.timestamp for r in bag.refs] == pytest.approx([r.timestamp for r in tum.refs])
    frame, expected = bag.decode(bag.refs[1]), tum.decode(tum.refs[1])
    assert frame.color.shape == (24, 32, 3) and np.array_equal(frame.color, expected.color)
    assert np.allclose(frame.intrinsics, expected.intrinsics) and np.allclose(frame.c2w_gt, expected.c2w_gt)  # type: ignore[arg-type]


def test_poses_as_the_starting_guess_of_tracking(bags: dict[str, Path], tum_seq: Path) -> None:
    bag = open_dataset(_config(bags["ros1.bag"], pose_use="initial_guess"))
    tum = TumFolder.read(tum_seq)
    frames = [bag.decode(ref) for ref in bag.refs]
    assert all(f.c2w_gt is None for f in frames)  # no ATE reference
    for frame, pose in zip(frames, tum.poses):
        assert frame.c2w_prior is not None and np.allclose(frame.c2w_prior, pose, atol=1e-6)
    assert all(
        f.c2w_prior is None for f in map(open_dataset(_config(bags["ros1.bag"], pose_use="ignore")).decode, bag.refs)
    )


@pytest.fixture(scope="session")
def tum_run(tum_seq: Path, tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    out = tmp_path_factory.mktemp("runs")
    assert (
        main(["run", str(tum_seq), "--preset", "tiny", "--output", str(out), "--name", "tum", "-q", *FIRST_FRAMES]) == 0
    )
    return read_tum_trajectory(out / "tum" / "trajectory.txt")[1]


@pytest.mark.slow
@pytest.mark.parametrize("name", list(TOPICS))
def test_a_bag_runs_end_to_end_as_its_tum_folder(
    name: str, bags: dict[str, Path], tum_run: np.ndarray, tmp_path: Path
) -> None:
    settings = [f"--set=dataset.pose_frames={','.join(v)}" for k, v in TOPICS[name].items()]
    argv = [
        "run",
        str(bags[name]),
        "--preset",
        "tiny",
        "--output",
        str(tmp_path),
        "--name",
        "bag",
        "-q",
        *settings,
        *FIRST_FRAMES,
    ]
    assert main(argv) == 0
    poses = read_tum_trajectory(tmp_path / "bag" / "trajectory.txt")[1]
    assert poses.shape == tum_run.shape  # the same frames
    assert np.abs(poses[:, :3, 3] - tum_run[:, :3, 3]).max() < 0.005  # metres (16UC1 depth is rounded to mm)
    assert np.abs(poses[:, :3, :3] - tum_run[:, :3, :3]).max() < 0.01


def test_the_real_tum_sample_as_a_bag(tum_sample: Path, tmp_path: Path) -> None:
    """Skipped without the shared TUM sample: its frames through a ROS 1 bag, as the folder reads them."""
    folder = TumFolder.read(tum_sample, intrinsics=np.array([[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]]))
    bag = open_dataset(_config(write_tum_bag(tmp_path / "fr1.bag", folder, "ros1", depth="32FC1")))
    tum = open_dataset(DatasetConfig(path=str(tum_sample)))
    assert len(bag) == len(tum)
    for ours, theirs in list(zip(bag.refs, tum.refs))[::9]:
        frame, expected = bag.decode(ours), tum.decode(theirs)
        assert np.array_equal(frame.color, expected.color) and np.array_equal(frame.depth, expected.depth)
        assert np.allclose(frame.c2w_gt, expected.c2w_gt, atol=1e-6)  # type: ignore[arg-type]


def _fails(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """The one line a failing command prints (exit code 2)."""
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gsplatam: error: "), lines
    return lines[0]


def _run(path: Path, tmp_path: Path, *settings: str) -> list[str]:
    return [
        "run",
        str(path),
        "--preset",
        "tiny",
        "--output",
        str(tmp_path / "out"),
        "-q",
        *[f"--set={s}" for s in settings],
    ]


def test_a_bag_without_depth_lists_its_topics(
    tum_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = TumFolder.read(tum_seq)
    folder.depths, folder.depth_t = [], np.zeros(0)
    path = write_tum_bag(tmp_path / "nodepth.bag", folder, "ros1")
    line = _fails(_run(path, tmp_path), capsys)
    assert "has no depth image topic; its topics: /camera/color/camera_info (sensor_msgs/CameraInfo)" in line
    assert "/camera/color/image_raw (sensor_msgs/Image)" in line and "/camera/pose (geometry_msgs/PoseStamped)" in line


def test_a_named_topic_that_is_absent_or_ambiguous_topics_are_one_line(
    bags: dict[str, Path], tum_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    line = _fails(_run(bags["ros1.bag"], tmp_path, "dataset.color_topic=/camera/rgb"), capsys)
    assert "has no topic /camera/rgb (dataset.color_topic); its topics: " in line
    folder = TumFolder.read(tum_seq)

    def second_camera(bag: BagWriter) -> None:
        bag.put("/camera2/color/image_raw", bag.image(folder.color_t[0], folder.colors[0], "rgb8"), 1)

    path = write_tum_bag(tmp_path / "two.bag", folder, "ros1", edit=second_camera)
    line = _fails(_run(path, tmp_path), capsys)
    assert "has 2 colour image topics (/camera/color/image_raw, /camera2/color/image_raw)" in line
    assert "--set dataset.color_topic=TOPIC" in line
    named = open_dataset(_config(path, color_topic="/camera/color/image_raw"))
    assert len(named) == len(folder.colors)


def test_depth_of_another_size_than_colour_is_one_line(
    tum_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = TumFolder.read(tum_seq)
    folder.depths = [raw[::2, ::2].copy() for raw in folder.depths]  # the depth camera's own size
    path = write_tum_bag(tmp_path / "sizes.bag", folder, "ros1")
    line = _fails(_run(path, tmp_path), capsys)
    assert (
        "depth on /camera/aligned_depth_to_color/image_raw is 32x24, colour on /camera/color/image_raw is 64x48" in line
    )
    assert "depth must be registered to colour" in line


def test_an_unknown_depth_encoding_is_one_line(
    tum_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_tum_bag(tmp_path / "encoding", TumFolder.read(tum_seq), "mcap", depth="64FC1")
    line = _fails(_run(path, tmp_path), capsys)
    assert "/camera/aligned_depth_to_color/image_raw: unknown depth encoding '64FC1'" in line
    assert "16UC1 millimetres or 32FC1 metres" in line


@pytest.mark.parametrize("name", ["ros1.bag", "file.mcap"])
def test_a_truncated_bag_is_one_line(
    name: str, bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cut = tmp_path / name
    data = bags[name].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    line = _fails(_run(cut, tmp_path, *(f"dataset.{k}={','.join(v)}" for k, v in TOPICS[name].items())), capsys)
    assert f"cannot open the bag {cut} (truncated or corrupt?)" in line


def test_compressed_depth_is_read_as_compressed_depth_image_transport_writes_it() -> None:
    """A `16UC1; compressedDepth png` CompressedImage: a 12-byte header, then a 16-bit PNG of millimetres."""
    millimetres = np.array([[0, 1000], [1500, 65535]], dtype=np.uint16)
    png = cv2.imencode(".png", millimetres)[1].reshape(-1)
    message = SimpleNamespace(format="16UC1; compressedDepth png", data=np.concatenate([np.zeros(12, np.uint8), png]))
    depth = ros_messages.depth_array(message, ros_messages.COMPRESSED)
    assert np.array_equal(depth, millimetres.astype(np.float32) * np.float32(0.001))
    message.format = "32FC1; compressedDepth rvl"
    with pytest.raises(DataError, match="unknown compressed depth format '32FC1; compressedDepth rvl'"):
        ros_messages.depth_array(message, ros_messages.COMPRESSED)
