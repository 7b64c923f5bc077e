"""Loop closure's front half: whether the newest keyframe sees again what an old one saw.

At each new keyframe, the candidates (`loop_candidates`: near by the current estimates, at
least `min_keyframes_back` older, the most alike first) are each verified by dense RGB-D
alignment of the current keyframe against the candidate's stored colour and depth
(`rgbd_alignment`; the candidate plays the render, its silhouette 1 where its depth is valid),
started from the relative pose the estimates imply and judged as the tracker judges itself
(`SolveReport`, under the `loops.*` limits): first at the coarse pyramid levels, kept for every
keyframe (`views.KeyframeViews`), and only then at the finest. A verified candidate is accepted
only when a second verified loop puts the current keyframe at the same place: another
candidate of the same keyframe, or a loop one of the last `confirm_keyframes` keyframes
verified, carried to this one by the estimates (two views agreeing on one pose are rarely both
wrong; a real revisit is seen by consecutive keyframes, and one old keyframe may be all that
each of them sees again). The pose graph then keeps an accepted loop only if its optimum agrees
with it (`pose_graph.optimise`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import Enum

import torch

from pipeline.config import LoopConfig, TrackingConfig
from pipeline.geometry import grid_around, invert_pose
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.candidates import LoopCandidate, loop_candidates
from pipeline.slam.loops.pose_graph import Edge, GraphSolution, MotionSize, alignment_information, motion_size
from pipeline.slam.loops.views import KeyframeViews
from pipeline.slam.tracking.align_tracker import SolveReport, level_params, read_report
from pipeline.slam.tracking.rgbd_alignment import (
    EAGER_ALIGN,
    AlignKernels,
    AlignParams,
    SourcePoints,
    TargetMaps,
    align,
    solve_of,
)

NO_INFORMATION = torch.zeros(6, 6, dtype=torch.float64)  # of a verification that failed at its coarse levels


class Verdict(Enum):
    ACCEPTED = "accepted"
    FAILED_VERIFICATION = "failed verification"  # the alignment judged itself unsound
    UNCONFIRMED = "unconfirmed"  # verified, but no second verified candidate agrees


@dataclass(frozen=True)
class Verification:
    """The dense alignment of the current keyframe to an old one."""

    report: SolveReport
    coverage: float  # inliers / valid-depth pixels of the current keyframe
    relative: torch.Tensor  # [4, 4] float64: the current camera in the old one's, as aligned
    information: torch.Tensor  # [6, 6] float64 of `relative` (pose_graph's convention)
    failure: str  # empty when verified


@dataclass(frozen=True)
class LoopCheck:
    """One candidate's verification and verdict."""

    candidate: LoopCandidate
    verification: Verification
    verdict: Verdict
    reason: str  # why not accepted; empty when accepted

    @property
    def verified(self) -> bool:
        return self.verdict is not Verdict.FAILED_VERIFICATION


@dataclass(frozen=True)
class LoopDetection:
    """What one keyframe's loop search found."""

    current: int  # the current keyframe's position
    checks: tuple[LoopCheck, ...]  # one per candidate, most similar first

    @property
    def detected(self) -> int:
        return len(self.checks)

    @property
    def verified(self) -> int:
        return sum(check.verified for check in self.checks)

    @property
    def accepted(self) -> int:
        return sum(check.verdict is Verdict.ACCEPTED for check in self.checks)

    @property
    def rejected(self) -> int:
        return self.detected - self.accepted

    def sightings(self, keyframes: Sequence[Keyframe]) -> list[Sighting]:
        """Its verified loops as `Sighting`s (`keyframes`: the store it searched)."""
        current = keyframes[self.current]
        seen_from = current.c2w.detach().to("cpu", torch.float64)
        return [
            Sighting(
                keyframes[check.candidate.position].pose.position,
                current.pose.position,
                check.verification.relative,
                seen_from,
            )
            for check in self.checks
            if check.verified
        ]

    def edges(self) -> tuple[Edge, ...]:
        """The accepted loops as pose-graph edges (candidate -> current)."""
        return tuple(
            Edge(
                check.candidate.position,
                self.current,
                check.verification.relative,
                check.verification.information,
                loop=True,
            )
            for check in self.checks
            if check.verdict is Verdict.ACCEPTED
        )


@dataclass(frozen=True)
class LoopTally:
    """Loop closure's counts over a run: candidates detected, verified by alignment, accepted
    (and kept by the pose graph), rejected, and why."""

    detected: int = 0
    verified: int = 0
    accepted: int = 0
    rejected: int = 0
    failed_verification: int = 0  # the alignment judged itself unsound
    unconfirmed: int = 0  # verified, but no second candidate agreed
    dropped_by_graph: int = 0  # accepted, then left out by the pose graph's optimum
    searches: int = 0  # keyframes searched (every keyframe kept)
    search_s: float = 0.0  # seconds over all searches: the odometry edge's alignment, candidates, verification
    search_max_s: float = 0.0  # the longest search: a compile or a stall that the mean hides
    search_wait_s: float = 0.0  # seconds over all searches waiting, before each, for the device's queued work

    def counted(self, detection: LoopDetection, seconds: float, waited: float = 0.0) -> LoopTally:
        """With one keyframe's search, which took `seconds` after `waited` for the device."""
        verdicts = [check.verdict for check in detection.checks]
        return replace(
            self,
            searches=self.searches + 1,
            search_s=self.search_s + seconds,
            search_max_s=max(self.search_max_s, seconds),
            search_wait_s=self.search_wait_s + waited,
            detected=self.detected + detection.detected,
            verified=self.verified + detection.verified,
            accepted=self.accepted + detection.accepted,
            rejected=self.rejected + detection.rejected,
            failed_verification=self.failed_verification + verdicts.count(Verdict.FAILED_VERIFICATION),
            unconfirmed=self.unconfirmed + verdicts.count(Verdict.UNCONFIRMED),
        )

    def optimised(self, solution: GraphSolution) -> LoopTally:
        """After a pose-graph optimisation: its dropped loops count as rejected, not accepted."""
        dropped = len(solution.dropped)
        return replace(
            self,
            accepted=self.accepted - dropped,
            rejected=self.rejected + dropped,
            dropped_by_graph=self.dropped_by_graph + dropped,
        )


@dataclass(frozen=True)
class ClosedLoop:
    """A loop closed: the pose graph optimised with its accepted edges, the map moved with it."""

    frame: int  # the current keyframe's frame index
    matched: tuple[int, ...]  # frame indices of the old keyframes whose loop edges the optimum kept
    correction: MotionSize  # the largest correction of a keyframe pose it made
    detect_s: float  # seconds: candidates and their verification
    correct_s: float  # seconds: the pose graph's optimisation and moving the map
    published_s: float  # seconds from the detection's start to the corrected map published


def closed_loop_line(loop: ClosedLoop) -> str:
    """The log line of a closed loop."""
    matched = ", ".join(str(frame) for frame in loop.matched)
    size = loop.correction
    return (
        f"loop closed at frame {loop.frame} with frame{'s' if len(loop.matched) > 1 else ''} {matched}: keyframes"
        f" moved up to {100 * size.translation_m:.1f} cm, {size.rotation_deg:.1f} deg; detection"
        f" {1000 * loop.detect_s:.0f} ms, correction {1000 * loop.correct_s:.0f} ms, corrected map published"
        f" {1000 * loop.published_s:.0f} ms after the detection began"
    )


def verification_limits(tracking: TrackingConfig, config: LoopConfig, level: int = 0) -> TrackingConfig:
    """The tracker's self-judgement under loop closure's limits, at pyramid level `level`: the
    residual limits widen with a coarser pixel's footprint, as the depth gate does."""
    return replace(
        tracking,
        align_min_inliers=config.min_inliers,
        align_min_conditioning=config.min_conditioning,
        align_max_residual_m=config.max_residual_m * 2**level,
        align_max_intensity_rms=config.max_intensity_rms,
    )


def judged(report: SolveReport, config: LoopConfig, tracking: TrackingConfig, level: int = 0) -> str:
    """Why a verification at pyramid level `level` fails (`SolveReport.failure` under
    `verification_limits`, and coverage: `min_coverage`); empty when it passes."""
    failure = report.failure(verification_limits(tracking, config, level))
    coverage = report.inliers / max(report.valid, 1)
    if not failure and coverage < config.min_coverage:
        failure = f"only {coverage:.0%} of the keyframe's pixels fit the old one (at least {config.min_coverage:.0%})"
    return failure


def verify(
    sources: Sequence[SourcePoints],
    views: KeyframeViews,
    old: Keyframe,
    starts: torch.Tensor,
    intrinsics: torch.Tensor,
    config: LoopConfig,
    tracking: TrackingConfig,
    schedule: tuple[int, ...] | None = None,
    kernels: AlignKernels = EAGER_ALIGN,
) -> Verification:
    """Align the current keyframe (`sources`, its pyramid as points, finest first) to `old` (its
    stored colour and depth as the target, `views`) from the relative pose(s) `starts` [4, 4] or
    [S, 4, 4] float64 (the current camera in the old one's: the estimates', or `start_poses`),
    over `schedule` (default `verify_iters`): the coarse levels first from every start (one
    batched solve, `kernels.batch`), judged (`judged` at level 1); of the starts that pass them,
    only the one of least RMS residual goes on to the finest level, judged in full (the finest
    level and its target, made again for an old keyframe, are most of a verification's cost:
    once per candidate, not once per start).
    None passing: the first start's failure."""
    schedule = schedule or config.verify_iters
    params = level_params(tracking, len(schedule))
    start = starts.reshape(-1, 4, 4)
    if len(schedule) > 1:
        fits = _coarse_fits(sources, views.coarse(old), params, schedule, start, config, tracking, kernels)
        passing = [fit for fit in fits if not fit.failure]
        if not passing:
            return fits[0]
        start = min(passing, key=lambda fit: fit.report.rms_m).relative[None].to(start)
    finest = views.finest(old, intrinsics)
    state = align(sources[:1], [finest], params[:1], schedule[-1:], kernels.one, start=start[0])
    report = read_report(state, sources[0].valid)
    information = alignment_information(state.fit.hessian, state.pose, config.information_scale)
    coverage = report.inliers / max(report.valid, 1)
    return Verification(report, coverage, state.pose.cpu(), information, judged(report, config, tracking))


def _coarse_fits(
    sources: Sequence[SourcePoints],
    coarse: Sequence[TargetMaps],
    params: Sequence[AlignParams],
    schedule: tuple[int, ...],
    starts: torch.Tensor,
    config: LoopConfig,
    tracking: TrackingConfig,
    kernels: AlignKernels,
) -> list[Verification]:
    """The coarse levels (1 and up) of a verification from each of `starts` [S, 4, 4] float64
    (one solve for all, `kernels.batch`), each judged at level 1 (no information: an edge is
    made at the finest level only). A single start is solved by `kernels.one`: the batched
    iteration is compiled for the tracker's grid of starts, and one start would compile it again
    in the middle of a run (16 s in one search on the H200, e15cbe0)."""
    if len(starts) == 1:
        states = [align(sources[1:], coarse, params[1:], schedule[:-1], kernels.one, start=starts[0])]
    else:
        solves = align(sources[1:], coarse, params[1:], schedule[:-1], kernels.batch, start=starts)
        states = [solve_of(solves, index) for index in range(len(starts))]
    fits = []
    for state in states:
        report = read_report(state, sources[1].valid)
        failure = judged(report, config, tracking, level=1)
        fits.append(
            Verification(report, report.inliers / max(report.valid, 1), state.pose.cpu(), NO_INFORMATION, failure)
        )
    return fits


def relative_pose(old: Keyframe, current: Keyframe) -> torch.Tensor:
    """[4, 4] float64: the `current` camera in the `old` one's, as their estimates put them."""
    return invert_pose(old.c2w.detach().double()) @ current.c2w.detach().double()


def start_poses(candidate: LoopCandidate, old: Keyframe, current: Keyframe, config: LoopConfig) -> torch.Tensor:
    """Where a candidate's verification starts, [S, 4, 4] float64 (the current camera in the old
    one's): the estimates' relative pose for a candidate near by them; for one found by its look
    alone, whose estimates may be metres off, the identity (alike views are likely seen from
    nearby) and the camera moved `appearance_offset_m` sideways and along its axis around it (a
    3 x 3 grid). On the cabinet's loop the identity alone ended in a minimum 11-19 cm from the
    truth that still passed, the best of the grid 1-3 cm from it; image features between the
    two keyframes found the loop in one pair of four at 640x480 (bench/NOTES.md)."""
    estimates = relative_pose(old, current)
    if not candidate.by_appearance:
        return estimates[None]
    return grid_around(torch.eye(4, dtype=torch.float64), config.appearance_offset_m).to(estimates)


def implied_pose(old: Keyframe, relative: torch.Tensor) -> torch.Tensor:
    """The current keyframe's camera-to-world [4, 4] float64 that an alignment to `old` implies."""
    return old.c2w.detach().to("cpu", torch.float64) @ relative


def agree(a: torch.Tensor, b: torch.Tensor, config: LoopConfig) -> bool:
    """Whether two camera-to-world poses [4, 4] lie within `agree_m` and `agree_deg`."""
    difference = motion_size(invert_pose(a) @ b)
    return difference.translation_m <= config.agree_m and difference.rotation_deg <= config.agree_deg


@dataclass(frozen=True)
class Sighting:
    """A loop an earlier search verified (a keyframe's, or a lost frame's): kept for
    `loops.confirm_keyframes` searches, so that a later verified loop that puts the cameras where
    this one does confirms it."""

    old: int  # the old keyframe's frame position
    current: int  # the frame position of the keyframe (or lost frame) that saw it
    relative: torch.Tensor  # [4, 4] float64: that camera in the old one's, as aligned
    seen_from: torch.Tensor  # [4, 4] float64: that camera's camera-to-world as estimated then

    def implied(self, keyframes: Sequence[Keyframe]) -> torch.Tensor | None:
        """The newest of `keyframes`' camera-to-world [4, 4] float64 that this loop implies: the
        pose it gives the camera that saw it, carried to the newest by their estimates' relative
        pose (the seer's estimate now where it is a stored keyframe, else `seen_from`: a lost
        frame is never stored); None when the old keyframe has left the store."""
        stored = {keyframe.pose.position: keyframe for keyframe in keyframes}
        old = stored.get(self.old)
        if old is None:
            return None
        seen_by = stored.get(self.current)
        seer = self.seen_from if seen_by is None else seen_by.c2w.detach().to("cpu", torch.float64)
        newest = keyframes[-1].c2w.detach().to("cpu", torch.float64)
        return implied_pose(old, self.relative) @ invert_pose(seer) @ newest


def detect_loops(
    keyframes: Sequence[Keyframe],
    views: KeyframeViews,
    sources: Sequence[SourcePoints],
    intrinsics: torch.Tensor,
    pixels: torch.Tensor,
    config: LoopConfig,
    tracking: TrackingConfig,
    sightings: Sequence[Sighting] = (),
    kernels: AlignKernels = EAGER_ALIGN,
    lost: bool = False,
) -> LoopDetection:
    """The loop search for the newest of `keyframes` (its pyramid as points: `sources`; the
    stored keyframes' descriptors and targets: `views`): candidates (`loop_candidates`), each
    verified (`verify`), the verified ones accepted where another verified candidate, or a
    loop an earlier keyframe verified (`sightings`), agrees on the current keyframe's pose
    (`agree`); `lost`: the newest is a frame tracking lost (`loop_candidates`)."""
    current = keyframes[-1]
    candidates = loop_candidates(keyframes, views.descriptors(list(keyframes)), intrinsics, pixels, config, lost)
    device = sources[0].points.device
    verifications = [
        verify(
            sources,
            views,
            keyframes[c.position],
            start_poses(c, keyframes[c.position], current, config).to(device),
            intrinsics,
            config,
            tracking,
            kernels=kernels,
        )
        for c in candidates
    ]
    implied = [implied_pose(keyframes[c.position], v.relative) for c, v in zip(candidates, verifications)]
    earlier = [pose for pose in (sighting.implied(keyframes) for sighting in sightings) if pose is not None]
    checks = [
        LoopCheck(candidate, verification, verdict, reason)
        for candidate, verification, (verdict, reason) in zip(
            candidates, verifications, verdicts(verifications, implied, config, earlier)
        )
    ]
    return LoopDetection(len(keyframes) - 1, tuple(checks))


def verdicts(
    verifications: Sequence[Verification],
    implied: Sequence[torch.Tensor],
    config: LoopConfig,
    earlier: Sequence[torch.Tensor] = (),
) -> list[tuple[Verdict, str]]:
    """Per candidate, (verdict, why not accepted): failed verification; else accepted when
    another verified candidate's implied pose of the current keyframe (`implied`, [4, 4]
    float64 each), or one that an earlier keyframe's verified loop implies (`earlier`), agrees
    with its own; else unconfirmed."""
    sound = [not verification.failure for verification in verifications]
    result = []
    for k, verification in enumerate(verifications):
        others = [implied[j] for j in range(len(implied)) if sound[j] and j != k]
        if not sound[k]:
            result.append((Verdict.FAILED_VERIFICATION, verification.failure))
        elif any(agree(implied[k], other, config) for other in [*others, *earlier]):
            result.append((Verdict.ACCEPTED, ""))
        else:
            result.append((Verdict.UNCONFIRMED, "no second verified loop puts the keyframe at the same pose"))
    return result
