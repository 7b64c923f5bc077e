"""Recovery after a lost frame: the next guess from the last good frame, relocalisation from keyframes."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from pipeline.config import DatasetConfig, SyntheticConfig, TrackingConfig, load_config, with_dataset_defaults
from pipeline.frame import DeviceFrame
from pipeline.geometry import constant_velocity, invert_pose
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.render import Gaussians, make_renderer
from pipeline.slam.keyframes import Keyframe, relocalisation_picks
from pipeline.slam.map_version import MapVersion
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.tracking.frontend import TrackingFrontend
from pipeline.slam.tracking.trackers import TrackResult
from pipeline.slam.tracking.trajectory import TrackingState
from pipeline.stages.upload import host_frame_tensors

CPU = torch.device("cpu")


def shifted(x: float) -> torch.Tensor:
    """[4, 4] camera-to-world: the identity moved x metres along the world's x axis."""
    pose = torch.eye(4)
    pose[0, 3] = x
    return pose


class StubTracker:
    """Returns the scripted pose of each call (lost when its failure is set) and records the guesses."""

    def __init__(self, script: list[tuple[torch.Tensor, str]]) -> None:
        self.script = script
        self.guesses: list[torch.Tensor] = []

    def __call__(
        self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, large_step: bool = False
    ) -> TrackResult:
        c2w, failure = self.script[len(self.guesses)]
        self.guesses.append(c2w_init)
        return TrackResult(c2w, torch.zeros(()), torch.ones(()), failure)


class BasinTracker:
    """Converges to `truth` from guesses within `basin_m` of it, else stays put and fails."""

    def __init__(self, truth: torch.Tensor, basin_m: float) -> None:
        self.truth, self.basin_m = truth, basin_m

    def __call__(
        self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, large_step: bool = False
    ) -> TrackResult:
        if float(torch.linalg.norm(c2w_init[:3, 3] - self.truth[:3, 3])) < self.basin_m:
            return TrackResult(self.truth, torch.zeros(()), torch.ones(()))
        return TrackResult(c2w_init, torch.zeros(()), torch.ones(()), "only 0 pixels fit the map")


def frame(index: int) -> DeviceFrame:
    return DeviceFrame(index, index / 30.0, torch.zeros(4, 6, 3), torch.ones(4, 6), torch.eye(3), None)


def version(keyframes: tuple[Keyframe, ...] = ()) -> MapVersion:
    return MapVersion(1, None, None, keyframes)  # type: ignore[arg-type]  # the stub trackers never read the map


def test_after_a_lost_frame_the_guesses_are_the_last_good_pose_and_its_velocity_carried_on() -> None:
    """Frames 30 a second, 1 cm each; frame 3 is lost (its pose stays its guess, not the failed
    solve's 5 m). Frame 4 is tracked from frame 2's velocity carried over two intervals (4 cm)
    and from frame 2's pose; frame 5, one good frame since, from frame 4's pose (the velocity
    starts again from zero), frame 6 by constant velocity."""
    a, b, c, d = shifted(0.01), shifted(0.02), shifted(0.04), shifted(0.05)
    tracker = StubTracker([(a, ""), (b, ""), (shifted(5.0), "lost"), (c, ""), (c, ""), (d, ""), (d, "")])
    front = TrackingFrontend(tracker, replace(TrackingConfig(), relocalise_candidates=0), CPU)
    results = [front.track(frame(0), None).result] + [front.track(frame(i), version()).result for i in range(1, 7)]
    assert [bool(r.lost) for r in results] == [False, False, False, True, False, False, False]
    guesses = tracker.guesses
    torch.testing.assert_close(guesses[2], constant_velocity(a, b))  # two good frames: constant velocity
    torch.testing.assert_close(front.trajectory.poses[3], guesses[2])  # the lost frame keeps its guess
    torch.testing.assert_close(guesses[3], constant_velocity(a, b, 2.0))  # the velocity over two intervals
    torch.testing.assert_close(guesses[4], b)  # and the last good pose
    torch.testing.assert_close(guesses[5], c)  # one good frame since: no velocity
    torch.testing.assert_close(guesses[6], constant_velocity(c, d))  # two good in a row: velocity again


def test_a_lost_frame_is_relocalised_from_a_keyframe_only_when_candidates_are_allowed() -> None:
    """The camera is back at the start, 2 m from the last good pose: the tracker's basin (10 cm)
    holds only the first keyframe's pose. With candidates the frame is tracked from it (and the
    result says so); with none it stays lost, frame after frame."""
    keyframes = tuple(
        Keyframe(i, torch.zeros(4, 6, 3, dtype=torch.uint8), torch.ones(4, 6), shifted(0.5 * i), 100 + i)
        for i in range(5)
    )  # at positions of no frame tracked here (a frame at a keyframe's position takes the keyframe's pose)
    truth = shifted(0.03)
    for candidates, lost in ((2, [False, False, False]), (0, [True, True, True])):
        front = TrackingFrontend(
            BasinTracker(truth, 0.1), replace(TrackingConfig(), relocalise_candidates=candidates), CPU
        )
        front.trajectory.append(shifted(2.0), None, 0.0, TrackingState.TRACKED, None)
        results = [front.track(frame(i), version(keyframes)).result for i in range(1, 4)]
        assert [bool(r.lost) for r in results] == lost
        if candidates:
            assert results[0].relocalised_from == 0 and "relocalised from keyframe 0" in results[0].warning
            assert results[1].relocalised_from is None  # tracked from the relocalised pose
            torch.testing.assert_close(front.trajectory.poses[-1], truth)


def stamped(index: int, timestamp: float) -> DeviceFrame:
    return replace(frame(index), timestamp=timestamp)


def test_after_a_stall_the_pose_is_trusted_and_the_next_guess_repeats_only_the_time_since() -> None:
    """Frames at 30 per second, then 1.27 s without one (the live source kept the newest): the
    camera moved 38 cm, over `lost_translation_m` (30 cm) but not over 30 cm per frame interval
    since the last good frame, so the pose is kept; the next frame, one interval later, is
    guessed at 1/38 of that motion ahead, not all of it (which would be 38 cm off)."""
    truth = [(0.0, 0.0), (1 / 30, 0.01), (2 / 30, 0.02), (40 / 30, 0.40), (41 / 30, 0.41), (42 / 30, 0.42)]
    tracker = StubTracker([(shifted(x), "") for _, x in truth[1:]])  # the first frame is not tracked
    front = TrackingFrontend(tracker, replace(TrackingConfig(), relocalise_candidates=0), CPU)
    results = [front.track(stamped(i, t), version() if i else None).result for i, (t, _) in enumerate(truth)]
    assert [r.lost for r in results] == [""] * len(truth)
    guesses = tracker.guesses  # for frames 1 to 5
    torch.testing.assert_close(guesses[2], shifted(0.03))  # constant velocity over one interval
    torch.testing.assert_close(guesses[3], shifted(0.41), atol=1e-6, rtol=0)  # 1/38 of 0.02 -> 0.40
    torch.testing.assert_close(guesses[4], shifted(0.42), atol=1e-6, rtol=0)  # steady again


def test_a_jump_beyond_the_distance_the_time_allows_is_still_lost() -> None:
    """Two intervals after the last good frame, 30 cm per interval allows 60 cm: 70 cm is lost."""
    truth = [(0.0, 0.0), (1 / 30, 0.01), (2 / 30, 0.02), (4 / 30, 0.74)]
    tracker = StubTracker([(shifted(x), "") for _, x in truth[1:]])
    front = TrackingFrontend(tracker, replace(TrackingConfig(), relocalise_candidates=0), CPU)
    results = [front.track(stamped(i, t), version() if i else None).result for i, (t, _) in enumerate(truth)]
    assert [bool(r.lost) for r in results] == [False, False, False, True]
    assert "(at most 0.60 m)" in results[-1].lost


@pytest.mark.slow
def test_a_stall_of_35_frames_loses_no_frame(tmp_path: Path) -> None:
    """The generated room at 64x48 (1 cm per frame), the tiny preset: frames 0-3, then 38-41, as
    a live session sees a stall of 1.2 s. Before the guess and the jump limit knew the time, the
    first frame after the stall was judged lost ("pose jumped 0.39 m") and so was every later one."""
    path = tmp_path / "room"
    write_synthetic(path, SyntheticConfig(frames=42, width=64, height=48), progress=False)
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(path))).frames()]
    config = with_dataset_defaults(load_config("tiny"), "replica")
    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)
    results = [slam.step(frames[i]) for i in [0, 1, 2, 3, 38, 39, 40, 41]]
    assert [r.lost for r in results] == [""] * 8
    start = frames[0].c2w_gt
    assert start is not None
    for r in results[4:]:
        assert r.c2w_gt is not None
        moved = invert_pose(start) @ r.c2w_gt  # ground truth relative to the first frame, as SLAM's poses are
        assert float(torch.linalg.norm(r.c2w[:3, 3] - moved[:3, 3])) < 0.12  # frames 0-3 are ~8 cm off here


def test_relocalisation_picks_spread_over_the_store_and_cover_it_in_turn() -> None:
    assert relocalisation_picks(10, 3, 0) == [0, 4, 8]
    assert relocalisation_picks(10, 3, 1) == [1, 5, 9]
    assert sorted(sum((relocalisation_picks(10, 3, a) for a in range(4)), [])) == list(range(10))
    assert relocalisation_picks(10, 3, 4) == [0, 4, 8]  # then round again
    assert relocalisation_picks(2, 3, 0) == [0, 1]
    assert relocalisation_picks(0, 3, 0) == relocalisation_picks(5, 0, 0) == []


@pytest.mark.slow
def test_a_jump_back_to_the_start_is_recovered_with_relocalisation(tmp_path: Path) -> None:
    """8 frames of the generated room at 1 m/s (26 cm of path), 64x48, the tiny preset (align),
    then the stream loops back to its first 4 frames. `lost_translation_m` is 15 cm (4.5x a
    frame's motion, under the jump): from the last good pose each frame after the jump moves too
    far and is lost, frame after frame, without relocalisation; with it, the first keyframe's
    pose is tried and every frame after the jump is tracked, within 12 cm of ground truth
    (frames 0-7 themselves are 0-11 cm off at this size; measured: 5-6 cm after the jump)."""
    path = tmp_path / "fast"
    write_synthetic(path, SyntheticConfig(frames=8, width=64, height=48, seed=3, speed=1.0), progress=False)
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(path))).frames()]
    looped = [replace(f, index=8 + i) for i, f in enumerate(frames[:4])]

    def slam(candidates: int) -> SplaTAM:
        overrides = ["tracking.lost_translation_m=0.15", f"tracking.relocalise_candidates={candidates}"]
        config = with_dataset_defaults(load_config("tiny", overrides=overrides), "replica")
        return SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)

    recovering = slam(3)
    assert not any(recovering.step(f).lost for f in frames)
    stuck = slam(0)
    stuck.restore(recovering.checkpoint())
    assert all(stuck.step(f).lost for f in looped)

    after = [recovering.step(f) for f in looped]
    assert [bool(r.lost) for r in after] == [False] * 4 and after[0].relocalised_from is not None
    for r in after:
        assert r.c2w_gt is not None
        assert float(torch.linalg.norm(r.c2w[:3, 3] - r.c2w_gt[:3, 3])) < 0.12


def test_frames_follow_the_keyframe_they_were_tracked_after() -> None:
    """A frame's pose moves with its anchor (the newest keyframe of the version it was tracked
    against): unchanged keyframes leave every pose the very tensor tracking gave; a corrected one
    moves its frames by its correction, the next guess with them, and the poses as tracked stay."""
    correction = shifted(0.5)
    truth = [shifted(0.01 * i) for i in range(3)] + [correction @ shifted(0.03)]  # the last against the corrected map
    tracker = StubTracker([(pose, "") for pose in truth[1:]])
    front = TrackingFrontend(tracker, replace(TrackingConfig(), relocalise_candidates=0), CPU)
    front.track(frame(0), None)
    trajectory = front.trajectory
    keyframe = Keyframe(0, torch.zeros(4, 6, 3, dtype=torch.uint8), torch.ones(4, 6), trajectory.poses[0], 0)
    for i in (1, 2):
        front.track(frame(i), version((keyframe,)))
    assert all(a is b for a, b in zip(trajectory.poses_with([keyframe.pose]), trajectory.poses))
    moved = replace(keyframe, c2w=correction @ keyframe.c2w)
    followed = trajectory.poses_with([moved.pose])
    for position in (1, 2):
        torch.testing.assert_close(followed[position], correction @ trajectory.poses[position])
    torch.testing.assert_close(followed[0], moved.c2w)
    front.track(frame(3), version((moved,)))
    guess = tracker.guesses[-1]  # constant velocity from the corrected poses of frames 1 and 2
    torch.testing.assert_close(guess, correction @ shifted(0.03))
    assert front.state().tracked_poses is not None
    torch.testing.assert_close(front.state().tracked_poses, torch.stack([torch.eye(4), *truth[1:]]))


def test_a_frame_keeps_its_anchors_pose_not_the_versions_stack_of_poses() -> None:
    """The process schedule's reader gives keyframe poses as rows of one stacked tensor per
    version: a frame's anchor copies its row (a long live session would otherwise keep every
    version's stack alive); a pose of its own (the sequential schedule's) is kept as it is."""
    stack = torch.stack([shifted(0.1), shifted(0.2)])
    rows = tuple(Keyframe(i, torch.zeros(4, 6, 3, dtype=torch.uint8), torch.ones(4, 6), stack[i], i) for i in range(2))
    anchor = TrackingFrontend._anchor(version(rows))
    assert anchor is not None and anchor.position == 1 and torch.equal(anchor.c2w, stack[1])
    assert anchor.c2w._base is None and anchor.c2w.untyped_storage().data_ptr() != stack.untyped_storage().data_ptr()
    own = (Keyframe(0, torch.zeros(4, 6, 3, dtype=torch.uint8), torch.ones(4, 6), shifted(0.3), 0),)
    kept = TrackingFrontend._anchor(version(own))
    assert kept is not None and kept.c2w is own[0].c2w
    assert TrackingFrontend._anchor(None) is None and TrackingFrontend._anchor(version()) is None
