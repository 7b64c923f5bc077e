"""Loop closure's front half: which old keyframes the current one may see again, and whether it
does.

At each new keyframe: candidates are the keyframes at least `min_keyframes_back` older whose
cameras are near the current one by the current estimates (centre distance, viewing angle, and
the share of the current keyframe's pixels that land in their images, `overlap_fractions`),
ranked by the similarity of a global descriptor (a small, blurred, zero-mean thumbnail of
intensity, compared by correlation, as PTAM's relocaliser compares small blurry images). Each is verified by dense RGB-D alignment of the current keyframe against the
candidate's stored colour and depth (`rgbd_alignment`; the candidate plays the render, its
silhouette 1 where its depth is valid), started from the relative pose the estimates imply and
judged as the tracker judges itself (`SolveReport`, under the `loops.*` limits). A verified
candidate is accepted only when a second verified candidate puts the current keyframe at the
same place: two old views agreeing on one pose are rarely both wrong. The pose graph then keeps
an accepted loop only if its optimum agrees with it (`pose_graph.optimise`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import Enum

import torch
import torch.nn.functional as F

from pipeline.config import LoopConfig, TrackingConfig
from pipeline.geometry import invert_pose
from pipeline.slam.align_tracker import SolveReport, level_params, prepare_rgbd, read_report
from pipeline.slam.keyframes import Keyframe, overlap_fractions
from pipeline.slam.pose_graph import Edge, GraphSolution, alignment_information
from pipeline.slam.pyramid import check_pyramid_fits, intensity
from pipeline.slam.rgbd_alignment import align

THUMBNAIL = (12, 16)  # rows, columns of the descriptor's thumbnails
BLUR_SIGMA = 2.0  # thumbnail pixels: a small shift of the view changes the thumbnail little


@dataclass(frozen=True)
class LoopCandidate:
    """An old keyframe near the current one, by the current estimates."""

    position: int  # in the keyframes passed (the pose graph's node)
    similarity: float  # descriptor correlation, -1 to 1
    distance_m: float  # between the camera centres
    angle_deg: float  # between the viewing directions
    overlap: float  # fraction of the current keyframe's sampled pixels inside its image


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

    def edges(self) -> tuple[Edge, ...]:
        """The accepted loops as pose-graph edges (candidate -> current)."""
        return tuple(
            Edge(
                check.candidate.position,
                self.current,
                check.verification.relative,
                check.verification.information,
                True,
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

    def counted(self, detection: LoopDetection) -> LoopTally:
        verdicts = [check.verdict for check in detection.checks]
        return replace(
            self,
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


def blurred_thumbnail(image: torch.Tensor) -> torch.Tensor:
    """[H, W] -> [THUMBNAIL] by area averaging, then a Gaussian blur of BLUR_SIGMA."""
    small = F.adaptive_avg_pool2d(image[None, None], THUMBNAIL)
    radius = math.ceil(2 * BLUR_SIGMA)
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-0.5 * (offsets / BLUR_SIGMA) ** 2)
    kernel = kernel / kernel.sum()
    small = F.conv2d(F.pad(small, [radius, radius, 0, 0], mode="replicate"), kernel.view(1, 1, 1, -1))
    small = F.conv2d(F.pad(small, [0, 0, radius, radius], mode="replicate"), kernel.view(1, 1, -1, 1))
    return small[0, 0]


def standardised(values: torch.Tensor) -> torch.Tensor:
    """Flattened, zero mean and unit norm (zeros when constant)."""
    flat = values.reshape(-1)
    flat = flat - flat.mean()
    return flat / flat.norm().clamp(min=1e-12)


def descriptor(color: torch.Tensor) -> torch.Tensor:
    """A keyframe's global descriptor [12 x 16] from its colour [H, W, 3] in [0, 1]: the
    intensity's blurred thumbnail, zero mean and norm 1, so that the dot product of two is
    their correlation (a change of exposure does not count). Measured against ORB words and
    against adding inverse depth on generated loops (bench/loop_descriptors.py): as good at
    ranking the views near a keyframe, and needs no vocabulary."""
    return standardised(blurred_thumbnail(intensity(color)))


def _viewing_angles_deg(c2w: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Degrees between the optical axis of `c2w` [4, 4] and those of `poses` [K, 4, 4]."""
    cosine = (poses[:, :3, 2] * c2w[:3, 2]).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cosine))


def loop_candidates(
    keyframes: Sequence[Keyframe],
    descriptors: torch.Tensor,
    intrinsics: torch.Tensor,
    pixels: torch.Tensor,
    config: LoopConfig,
) -> list[LoopCandidate]:
    """The old keyframes the newest of `keyframes` (oldest first, current estimates) may see
    again, most similar first, at most `max_candidates`: at least `min_keyframes_back` older,
    camera centre within `radius_m`, viewing direction within `max_angle_deg`, at least
    `min_overlap` of the current keyframe's sampled `pixels` (flat indices into its depth) in
    their images, descriptor similarity at least `min_similarity`. `descriptors` [K, D], one
    per keyframe (`descriptor`)."""
    old = len(keyframes) - config.min_keyframes_back
    if old <= 0:
        return []
    current = keyframes[-1]
    poses = torch.stack([keyframe.c2w for keyframe in keyframes[:old]]).double()
    c2w = current.c2w.double()
    distance = (poses[:, :3, 3] - c2w[:3, 3]).norm(dim=-1)
    angle = _viewing_angles_deg(c2w, poses)
    overlap = overlap_fractions(current.depth, intrinsics, current.c2w, poses.to(current.c2w), pixels).double()
    similarity = (descriptors[:old] @ descriptors[-1]).double()
    near = (distance <= config.radius_m) & (angle <= config.max_angle_deg) & (overlap >= config.min_overlap)
    passing = torch.nonzero(near & (similarity >= config.min_similarity))[:, 0]
    ranked = passing[torch.argsort(similarity[passing], descending=True)][: config.max_candidates]
    stats = torch.stack([similarity, distance, angle, overlap]).cpu()  # one read of [4, K]
    return [LoopCandidate(int(k), *(float(x) for x in stats[:, k])) for k in ranked.tolist()]


def verification_limits(tracking: TrackingConfig, config: LoopConfig) -> TrackingConfig:
    """The tracker's self-judgement under loop closure's stricter limits."""
    return replace(
        tracking,
        align_min_inliers=config.min_inliers,
        align_min_conditioning=config.min_conditioning,
        align_max_residual_m=config.max_residual_m,
        align_max_intensity_rms=config.max_intensity_rms,
    )


def verify(
    current: Keyframe, old: Keyframe, intrinsics: torch.Tensor, config: LoopConfig, tracking: TrackingConfig
) -> Verification:
    """Align `current` (colour, depth) to `old` (its stored colour and depth as the target, valid
    depth as the silhouette), from the relative pose their estimates imply, over the
    `verify_iters` schedule; judged by `SolveReport.failure` under `verification_limits` and
    by coverage (`min_coverage`)."""
    levels = len(config.verify_iters)
    check_pyramid_fits(levels, current.depth.shape[0], current.depth.shape[1])
    silhouette = (old.depth > 0).to(old.depth.dtype)
    images = (current.color, current.depth, intrinsics, old.color, old.depth, silhouette)
    sources, targets = prepare_rgbd(*images, levels, tracking.align_min_silhouette)
    start = (invert_pose(old.c2w.double()) @ current.c2w.double()).to(sources[0].points.device)
    params = level_params(tracking, levels)
    state = align(sources, targets, params, config.verify_iters, start=start)
    report = read_report(state.fit, sources[0].valid)
    coverage = report.inliers / max(report.valid, 1)
    failure = report.failure(verification_limits(tracking, config))
    if not failure and coverage < config.min_coverage:
        failure = f"only {coverage:.0%} of the keyframe's pixels fit the old one (at least {config.min_coverage:.0%})"
    information = alignment_information(state.fit.hessian, state.pose, config.information_scale)
    return Verification(report, coverage, state.pose.cpu(), information, failure)


def implied_pose(old: Keyframe, relative: torch.Tensor) -> torch.Tensor:
    """The current keyframe's camera-to-world [4, 4] float64 that an alignment to `old` implies."""
    return old.c2w.detach().to("cpu", torch.float64) @ relative


def agree(a: torch.Tensor, b: torch.Tensor, config: LoopConfig) -> bool:
    """Whether two camera-to-world poses [4, 4] lie within `agree_m` and `agree_deg`."""
    difference = invert_pose(a) @ b
    cosine = ((torch.diagonal(difference[:3, :3]).sum() - 1) / 2).clamp(-1.0, 1.0)
    angle = math.degrees(math.acos(float(cosine)))
    return float(difference[:3, 3].norm()) <= config.agree_m and angle <= config.agree_deg


def detect_loops(
    keyframes: Sequence[Keyframe],
    descriptors: torch.Tensor,
    intrinsics: torch.Tensor,
    pixels: torch.Tensor,
    config: LoopConfig,
    tracking: TrackingConfig,
) -> LoopDetection:
    """The loop search for the newest of `keyframes`: candidates (`loop_candidates`), each
    verified (`verify`), the verified ones accepted where another verified one agrees on the
    current keyframe's pose (`agree`)."""
    current = keyframes[-1]
    candidates = loop_candidates(keyframes, descriptors, intrinsics, pixels, config)
    verifications = [verify(current, keyframes[c.position], intrinsics, config, tracking) for c in candidates]
    implied = [implied_pose(keyframes[c.position], v.relative) for c, v in zip(candidates, verifications)]
    checks = [
        LoopCheck(candidate, verification, verdict, reason)
        for candidate, verification, (verdict, reason) in zip(
            candidates, verifications, verdicts(verifications, implied, config)
        )
    ]
    return LoopDetection(len(keyframes) - 1, tuple(checks))


def verdicts(
    verifications: Sequence[Verification], implied: Sequence[torch.Tensor], config: LoopConfig
) -> list[tuple[Verdict, str]]:
    """Per candidate, (verdict, why not accepted): failed verification; else accepted when
    another verified candidate's implied pose of the current keyframe (`implied`, [4, 4]
    float64 each) agrees with its own; else unconfirmed."""
    sound = [not verification.failure for verification in verifications]
    result = []
    for k, verification in enumerate(verifications):
        if not sound[k]:
            result.append((Verdict.FAILED_VERIFICATION, verification.failure))
        elif any(sound[j] and j != k and agree(implied[k], implied[j], config) for j in range(len(implied))):
            result.append((Verdict.ACCEPTED, ""))
        else:
            result.append((Verdict.UNCONFIRMED, "no second verified candidate puts the keyframe at the same pose"))
    return result
