from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SMALL_SYNTH

from pipeline.config import DatasetConfig
from pipeline.errors import DataError, UserError
from pipeline.io.sources.datasets.depth_scale import check_depth_scale
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic import sequence
from pipeline.io.sources.datasets.tum import associate


def expected_frames() -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    intrinsics, frames = sequence(SMALL_SYNTH)
    return intrinsics, list(frames)


@pytest.mark.parametrize(
    "layout, depth_step, color_error", [("replica", 1 / 6553.5, 8.0), ("tum", 1 / 5000.0, 0.0)]
)  # Replica stores JPEG (lossy, 4:2:0 chroma on these 64x48 frames), TUM stores PNG (exact)
def test_synthetic_round_trip(
    layout: str, depth_step: float, color_error: float, replica_seq: Path, tum_seq: Path
) -> None:
    path = replica_seq if layout == "replica" else tum_seq
    dataset = open_dataset(DatasetConfig(path=str(path)))
    intrinsics, truth = expected_frames()
    assert dataset.format == layout and len(dataset) == SMALL_SYNTH.frames
    np.testing.assert_allclose(dataset.intrinsics, intrinsics)
    first = truth[0][2]
    for frame, (color, depth, c2w) in zip(dataset.frames(), truth):
        relative = np.linalg.inv(first) @ c2w
        np.testing.assert_allclose(frame.c2w_gt, relative, atol=1e-6 if layout == "tum" else 1e-9)
        assert frame.depth.dtype == np.float32 and frame.color.dtype == np.uint8
        assert np.abs(frame.depth - depth).max() <= depth_step / 2 + 1e-6
        assert np.abs(frame.color.astype(int) - color).mean() <= color_error
    np.testing.assert_allclose(next(iter(dataset.frames())).c2w_gt, np.eye(4), atol=1e-9)


def test_resize_and_slicing(replica_seq: Path) -> None:
    dataset = open_dataset(DatasetConfig(path=str(replica_seq), width=32, height=24, start=1, end=5, stride=2))
    frames = list(dataset.frames())
    assert [f.index for f in frames] == [0, 1] and frames[0].color.shape == (24, 32, 3)
    assert frames[0].intrinsics[0, 0] == pytest.approx(dataset.intrinsics[0, 0] / 2)
    np.testing.assert_allclose(frames[0].c2w_gt, np.eye(4), atol=1e-9)
    full = open_dataset(DatasetConfig(path=str(replica_seq)))
    depth = full.decode(full.refs[1]).depth
    assert set(np.unique(frames[0].depth)) <= set(np.unique(depth))  # nearest: no new depth values


def test_tum_association_nearest_within_window() -> None:
    color = np.array([1.00, 1.10, 1.18, 1.30])
    depth = np.array([1.01, 1.12, 1.40])
    poses = np.array([0.99, 1.11, 1.195, 1.31])
    # colour 1.30: the nearest depth (1.40) is 0.10 s away, beyond the 0.08 s window: dropped
    assert associate(color, depth, poses) == [(0, 0, 0), (1, 1, 1), (2, 1, 2)]
    assert associate(color, depth, None)[0] == (0, 0, -1)
    assert associate(color, np.array([5.0]), None) == []


def test_real_tum_sample(tum_sample: Path) -> None:
    dataset = open_dataset(DatasetConfig(path=str(tum_sample)))
    assert dataset.format == "tum" and len(dataset) == 37
    np.testing.assert_allclose(dataset.intrinsics[0, 0], 517.3)
    frames = list(dataset.frames())
    assert frames[0].color.shape == (480, 640, 3)
    valid = np.concatenate([f.depth[f.depth > 0] for f in frames])
    assert valid.min() >= 0.5 and valid.max() <= 4.0
    np.testing.assert_allclose(frames[0].c2w_gt, np.eye(4), atol=1e-9)
    assert 0.005 < np.linalg.norm(frames[-1].c2w_gt[:3, 3]) < 0.5


def copy_of(path: Path, tmp_path: Path) -> Path:
    target = tmp_path / path.name
    shutil.copytree(path, target)
    return target


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="dataset folder not found"):
        open_dataset(DatasetConfig(path=str(tmp_path / "nope")))


def test_unknown_layout(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="cannot tell the layout"):
        open_dataset(DatasetConfig(path=str(tmp_path)))


def test_missing_image_names_the_file_when_the_dataset_is_opened(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    (path / "results" / "depth000002.png").unlink()
    with pytest.raises(DataError, match="the depth image of frame 2 is missing: .*depth000002.png"):
        open_dataset(DatasetConfig(path=str(path)))
    assert len(open_dataset(DatasetConfig(path=str(path), end=2))) == 2  # only the frames used are checked


def test_a_missing_replica_colour_frame_is_named_not_counted(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    (path / "results" / "frame000003.jpg").unlink()
    with pytest.raises(DataError, match="the colour image of frame 3 is missing: .*frame000003.jpg"):
        open_dataset(DatasetConfig(path=str(path)))


def test_a_tum_listing_naming_a_missing_file_is_refused_at_open(tum_seq: Path, tmp_path: Path) -> None:
    path = copy_of(tum_seq, tmp_path)
    listed = (path / "depth.txt").read_text().split()[-1]  # the last frame's depth image
    (path / listed).unlink()
    with pytest.raises(DataError, match=f"the depth image of frame 5 is missing: {path / listed}"):
        open_dataset(DatasetConfig(path=str(path)))


def _in_millimetres(tum: Path, tmp_path: Path) -> Path:
    """A copy of the TUM sequence `tum` with its depth in millimetres (as a RealSense writes it)."""
    path = copy_of(tum, tmp_path)
    for image in (path / "depth").glob("*.png"):
        raw = cv2.imread(str(image), cv2.IMREAD_UNCHANGED).astype(np.float64)
        cv2.imwrite(str(image), np.rint(raw / 5000.0 * 1000.0).astype(np.uint16))
    return path


def test_dataset_depth_scale_reads_millimetre_depth(tum_seq: Path, tmp_path: Path) -> None:
    path = _in_millimetres(tum_seq, tmp_path)
    truth = list(open_dataset(DatasetConfig(path=str(tum_seq))).frames())
    as_mm = list(open_dataset(DatasetConfig(path=str(path), depth_scale=1000.0)).frames())
    at_tums = list(open_dataset(DatasetConfig(path=str(path))).frames())  # the layout's 5000: a fifth of the depth
    for mm, tums, expected in zip(as_mm, at_tums, truth):
        assert np.abs(mm.depth - expected.depth).max() <= 0.0005 + 1e-6  # a millimetre's rounding
        np.testing.assert_allclose(tums.depth * 5, mm.depth, rtol=1e-6)


def test_millimetre_depth_at_tums_scale_is_named_with_the_setting_that_fixes_it(
    tum_seq: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = _in_millimetres(tum_seq, tmp_path)
    config = DatasetConfig(path=str(path))
    with caplog.at_level("INFO", "gsplatam"):
        check_depth_scale(open_dataset(config), config)
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "median of 0.49 m at dataset.depth_scale=5000 (tum's default)" in warning
    assert "millimetres" in warning and "--set dataset.depth_scale=1000 (the median is then 2.45 m)" in warning
    caplog.clear()
    with caplog.at_level("DEBUG", "gsplatam"):
        right = DatasetConfig(path=str(path), depth_scale=1000.0)
        check_depth_scale(open_dataset(right), right)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    assert "median of 2.45 m at dataset.depth_scale=1000 (set)" in caplog.text


def test_depth_far_outside_what_a_camera_sees_stops_the_run_before_slam(
    tum_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.app.cli import main

    path = copy_of(tum_seq, tmp_path)
    for image in (path / "depth").glob("*.png"):  # depth in centimetres: 500 cm read as 0.1 m
        raw = cv2.imread(str(image), cv2.IMREAD_UNCHANGED).astype(np.float64)
        cv2.imwrite(str(image), np.rint(raw / 5000.0 * 100.0).astype(np.uint16))
    out = tmp_path / "out"
    assert main(["run", str(path), "--output", str(out), "--quiet"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert (
        "a median of 0.049 m at dataset.depth_scale=5000" in line
        and "outside dataset.depth_range_m (0.1 to 20 m)" in line
    )
    assert not any(out.iterdir())  # no run folder: stopped before SLAM
    config = DatasetConfig(path=str(path), depth_range_m=())
    check_depth_scale(open_dataset(config), config)  # the check can be turned off


def test_a_moved_run_folder_finds_its_dataset_by_the_path_as_given(tum_seq: Path, tmp_path: Path, monkeypatch) -> None:
    from pipeline.config import load_config, with_absolute_dataset_path

    monkeypatch.chdir(tum_seq.parent)
    config = with_absolute_dataset_path(load_config("tiny", overrides=[f"dataset.path={tum_seq.name}"]))
    assert config.dataset.path == str(tum_seq) and config.dataset.path_as_given == tum_seq.name
    moved = DatasetConfig(path=str(tmp_path / "gone"), path_as_given=tum_seq.name)
    assert len(open_dataset(moved)) == SMALL_SYNTH.frames  # relative to here, where the absolute path is gone
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match=f"dataset folder not found: {tmp_path / 'gone'} \\(given as {tum_seq.name}\\)"):
        open_dataset(moved)


def test_unreadable_image(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    (path / "results" / "frame000001.jpg").write_bytes(b"not a jpeg")
    dataset = open_dataset(DatasetConfig(path=str(path)))
    with pytest.raises(DataError, match="unreadable image: .*frame000001.jpg"):
        dataset.decode(dataset.refs[1])


def test_depth_of_wrong_size_or_type(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    cv2.imwrite(str(path / "results" / "depth000001.png"), np.zeros((10, 10), np.uint16))
    cv2.imwrite(str(path / "results" / "depth000002.png"), np.zeros((48, 64), np.uint8))
    dataset = open_dataset(DatasetConfig(path=str(path)))
    with pytest.raises(DataError, match="depth000001.png is 10x10, colour is 64x48"):
        dataset.decode(dataset.refs[1])
    with pytest.raises(DataError, match="depth000002.png has type uint8"):
        dataset.decode(dataset.refs[2])


def test_nan_depth(tum_seq: Path, tmp_path: Path) -> None:
    path = copy_of(tum_seq, tmp_path)
    lines = (path / "depth.txt").read_text().splitlines()
    stamp, name = lines[2].split()
    depth = np.ones((48, 64), np.float32)
    depth[3, 4] = np.nan
    cv2.imwrite(str(path / "depth" / "bad.tiff"), depth)
    lines[2] = f"{stamp} depth/bad.tiff"
    (path / "depth.txt").write_text("\n".join(lines) + "\n")
    dataset = open_dataset(DatasetConfig(path=str(path)))
    with pytest.raises(DataError, match="bad.tiff holds NaN or infinite"):
        dataset.decode(dataset.refs[0])


def test_empty_association(tum_seq: Path, tmp_path: Path) -> None:
    path = copy_of(tum_seq, tmp_path)
    (path / "depth.txt").write_text("# nothing\n100.0 depth/x.png\n")
    with pytest.raises(DataError, match="no colour frame of .* has depth"):
        open_dataset(DatasetConfig(path=str(path)))


def test_malformed_trajectory(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    (path / "traj.txt").write_text("1 2 3\n")
    with pytest.raises(DataError, match="traj.txt:1: expected 16 numbers"):
        open_dataset(DatasetConfig(path=str(path)))


def test_tum_camera_from_folder_name(tum_seq: Path, tmp_path: Path) -> None:
    path = copy_of(tum_seq, tmp_path)
    (path / "intrinsics.txt").unlink()
    with pytest.raises(UserError, match="cannot tell the TUM camera"):
        open_dataset(DatasetConfig(path=str(path)))
    renamed = path.rename(tmp_path / "rgbd_dataset_freiburg2_desk")
    assert open_dataset(DatasetConfig(path=str(renamed))).intrinsics[0, 0] == pytest.approx(520.9)
    explicit = open_dataset(DatasetConfig(path=str(renamed), intrinsics=(1.0, 2.0, 3.0, 4.0)))
    assert explicit.intrinsics[1, 1] == 2.0


def test_tum_lists_out_of_timestamp_order_are_sorted_with_a_warning(tum_seq: Path, tmp_path: Path, caplog) -> None:
    path = copy_of(tum_seq, tmp_path)
    lines = (path / "rgb.txt").read_text().splitlines()
    header, rows = (
        [line for line in lines if line.startswith("#")],
        [line for line in lines if not line.startswith("#")],
    )
    (path / "rgb.txt").write_text("\n".join(header + rows[::-1]) + "\n")
    with caplog.at_level("WARNING", "gsplatam"):
        dataset = open_dataset(DatasetConfig(path=str(path)))
    assert "rgb.txt: timestamps out of order; sorted" in caplog.text
    in_order = open_dataset(DatasetConfig(path=str(tum_seq)))
    assert [r.timestamp for r in dataset.refs] == [r.timestamp for r in in_order.refs]
    assert [r.color_path.name for r in dataset.refs] == [r.color_path.name for r in in_order.refs]


@pytest.mark.parametrize("resize", [None, (32, 24)])
def test_a_frame_of_another_size_mid_sequence_is_refused_by_name(
    replica_seq: Path, tmp_path: Path, resize: tuple[int, int] | None
) -> None:
    path = copy_of(replica_seq, tmp_path)
    cv2.imwrite(str(path / "results" / "frame000003.jpg"), np.zeros((24, 32, 3), np.uint8))
    cv2.imwrite(str(path / "results" / "depth000003.png"), np.ones((24, 32), np.uint16))
    width, height = resize or (0, 0)
    dataset = open_dataset(DatasetConfig(path=str(path), width=width, height=height))
    assert dataset.decode(dataset.refs[2]).color.shape[:2] == (height or 48, width or 64)
    with pytest.raises(DataError, match="frame000003.jpg is 32x24, the sequence's frames are 64x48"):
        dataset.decode(dataset.refs[3])


def test_a_first_frame_without_valid_depth_is_refused_by_name(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    cv2.imwrite(str(path / "results" / "depth000000.png"), np.zeros((48, 64), np.uint16))
    dataset = open_dataset(DatasetConfig(path=str(path)))
    with pytest.raises(DataError, match="depth000000.png holds no valid depth"):
        dataset.decode(dataset.refs[0])
    later = open_dataset(DatasetConfig(path=str(path), start=1))  # the first frame kept is what counts
    assert (later.decode(later.refs[0]).depth > 0).any()


def test_a_replica_trajectory_with_fewer_poses_than_frames(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    rows = (path / "traj.txt").read_text().splitlines()
    (path / "traj.txt").write_text("\n".join(rows[:-2]) + "\n")
    with pytest.raises(DataError, match="traj.txt has 4 poses but .* holds 6 colour frames"):
        open_dataset(DatasetConfig(path=str(path)))


@pytest.mark.parametrize(
    "row, message",
    [
        ("nan 0 0 0 0 0 1", "NaN or infinite value"),
        ("0 0 inf 0 0 0 1", "NaN or infinite value"),
        ("0 0 0 0 0 0 0", "the quaternion qx qy qz qw is zero"),
    ],
)
def test_bad_ground_truth_poses_name_their_line_at_open(tum_seq: Path, tmp_path: Path, row: str, message: str) -> None:
    path = copy_of(tum_seq, tmp_path)
    lines = (path / "groundtruth.txt").read_text().splitlines()
    lines[3] = f"{lines[3].split()[0]} {row}"
    (path / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=f"groundtruth.txt:4: {message}"):
        open_dataset(DatasetConfig(path=str(path)))


def test_a_nan_in_a_replica_trajectory_names_its_line(replica_seq: Path, tmp_path: Path) -> None:
    path = copy_of(replica_seq, tmp_path)
    rows = (path / "traj.txt").read_text().splitlines()
    rows[1] = " ".join(["nan"] + rows[1].split()[1:])
    (path / "traj.txt").write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match="traj.txt:2: NaN or infinite value"):
        open_dataset(DatasetConfig(path=str(path)))


@pytest.mark.parametrize("values", ["0 32 32 24", "32 -32 32 24"])
def test_non_positive_intrinsics_in_the_file_are_refused(replica_seq: Path, tmp_path: Path, values: str) -> None:
    path = copy_of(replica_seq, tmp_path)
    (path / "intrinsics.txt").write_text(values + "\n")
    with pytest.raises(DataError, match="intrinsics.txt: fx fy cx cy must be positive"):
        open_dataset(DatasetConfig(path=str(path)))
