"""Mapping at keyframe rate (`mapping.rate=keyframe`, either schedule): which frames become
keyframes by what they add, and a run in which only they are densified and mapped."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from pipeline.config import DatasetConfig, KeyframeConfig, load_config, with_dataset_defaults
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.render import Gaussians, make_renderer
from pipeline.slam.keyframes import KeyframeChooser, KeyframePose, grid_pixels, novelty
from pipeline.slam.process.schedule import ProcessSplaTAM, start_process_slam
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.tracking.trackers import TrackResult
from pipeline.stages.frame_log import FrameLog
from pipeline.stages.upload import host_frame_tensors

CPU = torch.device("cpu")
WIDTH, HEIGHT, FOCAL, DEPTH_M = 64, 48, 40.0, 2.0  # a camera facing a wall 2 m away


def wall(depth_m: float = DEPTH_M) -> DeviceFrame:
    intrinsics = torch.tensor([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]])
    depth = torch.full((HEIGHT, WIDTH), depth_m)
    return DeviceFrame(0, 0.0, torch.zeros(HEIGHT, WIDTH, 3), depth, intrinsics, None)


def moved(x: float = 0.0, yaw_deg: float = 0.0) -> torch.Tensor:
    """[4, 4] camera-to-world: x metres along the camera's x axis, turned about its y axis."""
    pose = torch.eye(4)
    angle = math.radians(yaw_deg)
    pose[0, 0] = pose[2, 2] = math.cos(angle)
    pose[0, 2], pose[2, 0] = math.sin(angle), -math.sin(angle)
    pose[0, 3] = x
    return pose


def chooser(**settings: float) -> KeyframeChooser:
    chosen = KeyframeChooser(replace(KeyframeConfig(), **settings))
    chosen.kept(KeyframePose(0, torch.eye(4), 0))
    return chosen


def test_a_grid_covers_the_image_evenly() -> None:
    pixels = grid_pixels(HEIGHT, WIDTH, 48, CPU)  # stride 8: 6 rows of 8
    assert pixels.shape == (48,) and len(set(pixels.tolist())) == 48
    assert set((pixels % WIDTH).tolist()) == set(range(4, WIDTH, 8))
    assert torch.equal(grid_pixels(2, 3, 1600, CPU), torch.arange(6))  # fewer pixels than samples: all of them


def test_novelty_is_the_share_of_the_frame_outside_the_keyframe_and_the_motion_over_depth() -> None:
    """A sideways move of a quarter of the image's width at the wall leaves three quarters of the
    frame in the keyframe's view; the move over the wall's distance is `moved`."""
    frame = wall()
    same = novelty(frame.depth, frame.intrinsics, torch.eye(4), torch.eye(4), 1600)
    assert (same.overlap, same.moved) == (1.0, 0.0)
    quarter = WIDTH / 4 * DEPTH_M / FOCAL  # metres that shift the wall by a quarter of the image
    shifted = novelty(frame.depth, frame.intrinsics, moved(x=quarter), torch.eye(4), 1600)
    assert shifted.overlap == pytest.approx(0.75, abs=0.02)
    assert shifted.moved == pytest.approx(quarter / DEPTH_M, rel=1e-5)
    blind = novelty(torch.zeros(HEIGHT, WIDTH), frame.intrinsics, moved(x=1.0), torch.eye(4), 1600)
    assert (blind.overlap, blind.moved) == (1.0, 0.0)  # no valid depth: nothing to add


def test_a_frame_that_adds_little_is_no_keyframe_and_one_that_adds_enough_is() -> None:
    frame = wall()
    settings = {"min_overlap": 0.9, "max_translation": 0.08, "min_coverage": 0.5}
    assert chooser(**settings).reason(frame, moved(x=0.01), 1, 0.9, False) == ""  # 0.5% of the depth: little
    assert chooser(**settings).reason(frame, moved(yaw_deg=1.0), 1, 0.9, False) == ""
    assert "keyframe's view" in chooser(**settings).reason(frame, moved(yaw_deg=10.0), 1, 0.9, False)
    assert "median depth" in chooser(**settings).reason(frame, moved(x=0.2), 1, 0.9, False)  # 0.1 x the depth
    assert "map covers 30%" in chooser(**settings).reason(frame, torch.eye(4), 1, 0.3, False)
    assert chooser(**settings).reason(frame, torch.eye(4), 1, None, False) == ""  # coverage of an older map
    assert "last frame" in chooser(**settings).reason(frame, torch.eye(4), 1, 1.0, True)
    assert "first frame" in KeyframeChooser(KeyframeConfig()).reason(frame, torch.eye(4), 0, 1.0, False)


def test_keyframes_every_bounds_the_gap_between_keyframes() -> None:
    """A camera that stands still adds nothing: a keyframe comes `every` frames after the last,
    counted in the run's poses (a lost frame, never offered, counts too)."""
    still = chooser(every=4)
    reasons = {position: still.reason(wall(), torch.eye(4), position, 1.0, False) for position in range(1, 9)}
    assert [p for p, why in reasons.items() if why] == [4, 5, 6, 7, 8]
    assert "4 frames after the last keyframe" in reasons[4]
    still.kept(KeyframePose(6, torch.eye(4), 6))
    assert not still.reason(wall(), torch.eye(4), 9, 1.0, False) and still.reason(wall(), torch.eye(4), 10, 1.0, False)


GAP_ONLY = [  # keyframe rate where only the gap says which frame is a keyframe (every 2nd), fast settings
    "tracking.iters=3", "mapping.iters=3", "mapping.rate=keyframe", "keyframes.every=2",
    "keyframes.min_overlap=0", "keyframes.max_translation=1e9", "keyframes.min_coverage=0",
    "mapping.refine_pose_lr=1e-3",
]  # fmt: skip


def _frames(replica_seq: Path) -> list[DeviceFrame]:
    return [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()]


def _wall_in_a_run(replica_seq: Path) -> tuple[ProcessSplaTAM, list[DeviceFrame]]:
    """The process schedule at keyframe rate (`GAP_ONLY`), refinement on."""
    config = with_dataset_defaults(load_config("tiny", overrides=GAP_ONLY), "replica")
    return start_process_slam(config, CPU, live=False), _frames(replica_seq)


@pytest.mark.slow
def test_keyframe_rate_maps_keyframes_only_never_a_lost_frame_and_keeps_a_pose_per_frame(replica_seq: Path) -> None:
    """Six frames, every 2nd a keyframe, frame 2 lost (when its keyframe was due): mapping takes
    frames 0, 3 (the first good one after the gap) and 5 (the last), never the lost one; every
    frame has a pose; each frame between keyframes follows its keyframe's refinement (the final
    refinement moves the keyframes' poses): pose = keyframe now @ inv(keyframe as tracked) @ pose as tracked."""
    slam, frames = _wall_in_a_run(replica_seq)
    _losing_frame_2(slam)
    log = FrameLog()
    try:
        for frame in frames:
            log.add(slam.step(frame, is_last=frame.index == len(frames) - 1), 0.0)
        assert slam.finish(30) == 30  # 30 renders over 3 keyframes: each is seen
        results = log.results
        assert [bool(r.lost) for r in results] == [False, False, True, False, False, False]
        assert [r.mapped for r in results] == [True, False, False, True, False, True]
        assert [r.between_keyframes for r in results] == [False, True, False, False, True, False]
        assert log.unmapped_frames == 1  # the lost frame; the frames between keyframes are so by design
        assert [(report.index, report.mapped) for report in slam.mapping.mapped] == [(0, True), (3, True), (5, True)]
        assert sum(report.added > 0 for report in slam.mapping.mapped) >= 1  # densified at keyframes only
        checkpoint = slam.checkpoint()
        assert checkpoint.frames_done == len(slam.poses) == 6 and checkpoint.mapping.frames_seen == 3
        assert [k.index for k in checkpoint.keyframes] == [0, 3, 5]

        anchors = slam.frontend.trajectory.anchors
        assert [None if a is None else a.position for a in anchors] == [None, 0, 0, 0, 3, 3]
        poses, tracked = checkpoint.poses, checkpoint.tracking.tracked_poses  # one snapshot: refinement goes on
        assert tracked is not None
        for keyframe, stored in zip((3, 5), checkpoint.keyframes[1:]):  # the first keyframe stays: the gauge
            assert not torch.allclose(poses[keyframe], tracked[keyframe], atol=1e-7)  # refinement moved it
            assert torch.equal(poses[keyframe], stored.c2w.cpu())
        torch.testing.assert_close(poses[0], tracked[0])
        for position, keyframe in ((1, 0), (2, 0), (4, 3)):
            correction = poses[keyframe] @ invert_pose(tracked[keyframe])
            torch.testing.assert_close(poses[position], correction @ tracked[position])
        assert not torch.allclose(poses[4], tracked[4], atol=1e-7)
    finally:
        slam.close()


def _losing_frame_2(slam: ProcessSplaTAM | SplaTAM) -> None:
    """Make the tracker fail on frame 2 (a keyframe is due there)."""
    track = slam.frontend.tracker

    def losing(
        gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, large_step: bool = False
    ) -> TrackResult:
        result = track(gaussians, frame, c2w_init, large_step)
        return replace(result, failure="made to fail") if frame.index == 2 else result

    slam.frontend.tracker = losing


def test_sequential_at_keyframe_rate_maps_keyframes_only_and_refines_between_them(replica_seq: Path) -> None:
    """The sequential schedule at keyframe rate: the same keyframes as the process schedule's
    (0, 3 after the lost frame 2, the last 5), densified only there; each frame between
    keyframes runs `mapping.refine_between` renders over the keyframes (a new map version, no
    Gaussian added) and follows its keyframe; `auto` keeps sequential at frame rate."""
    config = with_dataset_defaults(load_config("tiny", overrides=[*GAP_ONLY, "mapping.refine_between=2"]), "replica")
    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)
    _losing_frame_2(slam)
    frames = _frames(replica_seq)
    results = [slam.step(frame, is_last=frame.index == len(frames) - 1) for frame in frames]
    assert [bool(r.lost) for r in results] == [False, False, True, False, False, False]
    assert [r.mapped for r in results] == [True, False, False, True, False, True]
    assert [r.between_keyframes for r in results] == [False, True, False, False, True, False]
    assert results[0].added > 0 and all(r.added == 0 for r in results if not r.mapped)
    assert results[1].map_version > results[0].map_version and results[1].gaussians == results[0].gaussians
    assert results[2].map_version == results[1].map_version  # the lost frame: neither mapped nor refined
    checkpoint = slam.checkpoint()
    assert [k.index for k in checkpoint.keyframes] == [0, 3, 5] and checkpoint.frames_done == len(slam.poses) == 6
    anchors = slam.frontend.trajectory.anchors
    assert [None if a is None else a.position for a in anchors] == [None, 0, 0, 0, 3, 3]
    plain = with_dataset_defaults(load_config("tiny", overrides=["mapping.rate=auto"]), "replica")
    assert SplaTAM(plain, make_renderer(plain.render, plain.gaussians, CPU), CPU).chooser is None
    resumed = SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)
    resumed.restore(checkpoint)  # the gap counts from the newest keyframe restored (5): 6 is between
    assert resumed.chooser is not None and resumed.chooser.last is not None and resumed.chooser.last.index == 5


@pytest.mark.slow
def test_after_a_resume_the_gap_counts_from_the_newest_keyframe_restored(replica_seq: Path) -> None:
    """A checkpoint after frames 0-2 (keyframes 0 and 2), restored into a fresh SLAM: frame 3 is
    between keyframes (one frame after keyframe 2, not a first frame), frame 4 the next keyframe."""
    slam, frames = _wall_in_a_run(replica_seq)
    try:
        for frame in frames[:3]:
            slam.step(frame)
        slam.finish(0)
        saved = slam.checkpoint()
    finally:
        slam.close()
    assert [k.index for k in saved.keyframes] == [0, 2]
    resumed, _ = _wall_in_a_run(replica_seq)
    try:
        resumed.restore(saved)
        results = [resumed.step(frame) for frame in frames[3:]]
        assert [r.mapped for r in results] == [False, True, False]
        assert resumed.chooser is not None and resumed.chooser.last is not None
        assert resumed.chooser.last.index == 4
    finally:
        resumed.close()


@pytest.mark.slow
def test_with_loops_on_the_process_schedule_hands_a_lost_frame_to_mapping_to_be_searched(replica_seq: Path) -> None:
    """Loops on, frame 2 lost: the mapping process is handed it too, searches it for a loop (no
    loop in four frames) and reports it not mapped; it is neither densified nor kept."""
    overrides = [*GAP_ONLY, "loops.enabled=true"]
    config = with_dataset_defaults(load_config("tiny", overrides=overrides), "replica")
    slam = start_process_slam(config, CPU, live=False)
    _losing_frame_2(slam)
    frames = _frames(replica_seq)[:4]
    try:
        results = [slam.step(frame, is_last=frame.index == 3) for frame in frames]
        assert slam.finish(0) == 0
        assert [bool(r.lost) for r in results] == [False, False, True, False]
        assert [(report.index, report.mapped, report.added) for report in slam.mapping.mapped] == [
            (0, True, slam.mapping.mapped[0].added), (2, False, 0), (3, True, slam.mapping.mapped[2].added),
        ]  # fmt: skip
        checkpoint = slam.checkpoint()
        assert [k.index for k in checkpoint.keyframes] == [0, 3]
        assert checkpoint.mapping.loops is not None and checkpoint.mapping.loops.tally.searches == 3
    finally:
        slam.close()
