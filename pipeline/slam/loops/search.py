"""The loop search over a run's keyframes, as the mapping side runs it at each keyframe kept:
the keyframe's views made once (`views.KeyframeViews`), its pyramid as points made once per
search and shared by its odometry edge and its candidates' verifications, and the loops the last
`loops.confirm_keyframes` keyframes verified carried to the next search (`detection.Sighting`)."""

from __future__ import annotations

import torch

from pipeline.config import LoopConfig, TrackingConfig
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.detection import LoopDetection, Sighting, Verification, detect_loops, relative_pose, verify
from pipeline.slam.loops.views import KeyframeViews
from pipeline.slam.tracking.align_tracker import source_pyramid
from pipeline.slam.tracking.pyramid import check_pyramid_fits
from pipeline.slam.tracking.rgbd_alignment import AlignIteration, SourcePoints, lm_iteration

ODOMETRY_SCHEDULE = (1,)  # the odometry edge: one linearisation at the finest level, at the estimates' relative pose


class LoopSearch:
    def __init__(self, config: LoopConfig, tracking: TrackingConfig, iteration: AlignIteration = lm_iteration) -> None:
        """`iteration`: the alignment's Levenberg-Marquardt iteration (the compiled one where
        `run.compile` says so, as the tracker's)."""
        self.config, self.tracking, self.iteration = config, tracking, iteration
        self.views = KeyframeViews(len(config.verify_iters), tracking.align_min_silhouette)
        self.sightings: list[Sighting] = []  # loops the last `confirm_keyframes` keyframes verified

    def kept(self, keyframes: list[Keyframe], intrinsics: torch.Tensor) -> list[SourcePoints]:
        """The newest of `keyframes` (the store, oldest first) was just kept: its view made (and
        those of a resumed run's stored keyframes) -> its pyramid as points, finest first."""
        current, levels = keyframes[-1], len(self.config.verify_iters)
        check_pyramid_fits(levels, current.depth.shape[0], current.depth.shape[1])
        self.views.update(keyframes, intrinsics)
        return source_pyramid(current.color, current.depth, intrinsics, levels)

    def odometry(
        self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor
    ) -> Verification:
        """The newest keyframe (`sources`) at the relative pose the estimates give it from the one
        before: the normal equations there, one linearisation at the finest level, judged as a
        verification is (the estimates are tracking's and mapping's; this only weighs them)."""
        previous, current = keyframes[-2], keyframes[-1]
        start = relative_pose(previous, current).to(sources[0].points.device)
        config, tracking = self.config, self.tracking
        return verify(
            sources, self.views, previous, start, intrinsics, config, tracking, ODOMETRY_SCHEDULE, self.iteration
        )

    def detect(
        self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor, pixels: torch.Tensor
    ) -> LoopDetection:
        """The loops of the newest keyframe (`sources`; `pixels`: flat indices of its sampled
        valid depth, for the candidates' overlap), confirmed by one another or by the loops the
        keyframes before verified (`detect_loops`); its own verified loops kept for the next."""
        detection = detect_loops(
            keyframes,
            self.views,
            sources,
            intrinsics,
            pixels,
            self.config,
            self.tracking,
            self.sightings,
            self.iteration,
        )
        recent = {keyframe.pose.position for keyframe in keyframes[len(keyframes) - self.config.confirm_keyframes :]}
        everything = [*self.sightings, *detection.sightings(keyframes)]
        self.sightings = [sighting for sighting in everything if sighting.current in recent]
        return detection
