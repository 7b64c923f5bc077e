"""The loop search over a run's keyframes, as the mapping side runs it at each keyframe kept
(and, where tracking lost a frame, from that frame: `LoopCloser.frame_lost`): the keyframe's
views made once (`views.KeyframeViews`), its pyramid as points made once per search and shared
by its odometry edge and its candidates' verifications, and the loops the last
`loops.confirm_keyframes` searches verified carried to the next (`detection.Sighting`)."""

from __future__ import annotations

from collections import deque

import torch

from pipeline.config import LoopConfig, TrackingConfig
from pipeline.geometry import grid_around
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.detection import (
    LoopDetection,
    Sighting,
    Verification,
    detect_loops,
    relative_pose,
    verify,
)
from pipeline.slam.loops.views import KeyframeViews
from pipeline.slam.tracking.align_tracker import source_pyramid
from pipeline.slam.tracking.pyramid import check_pyramid_fits
from pipeline.slam.tracking.rgbd_alignment import EAGER_ALIGN, AlignKernels, SourcePoints

ODOMETRY_SCHEDULE = (1,)  # the odometry edge: one linearisation at the finest level, at the estimates' relative pose


class LoopSearch:
    def __init__(self, config: LoopConfig, tracking: TrackingConfig, kernels: AlignKernels = EAGER_ALIGN) -> None:
        """`kernels`: the alignment's Levenberg-Marquardt iteration, from one start and from a
        batch (the compiled ones where `run.compile` says so, as the tracker's)."""
        self.config, self.tracking, self.kernels = config, tracking, kernels
        self.views = KeyframeViews(len(config.verify_iters), tracking.align_min_silhouette)
        self._recent: deque[list[Sighting]] = deque(maxlen=config.confirm_keyframes)  # per search, oldest first
        self._warmed = kernels is EAGER_ALIGN  # eager iterations need no warm-up

    @property
    def sightings(self) -> list[Sighting]:
        """The loops the last `confirm_keyframes` searches verified."""
        return [sighting for search in self._recent for sighting in search]

    def kept(self, keyframes: list[Keyframe], intrinsics: torch.Tensor) -> list[SourcePoints]:
        """The newest of `keyframes` (the store, oldest first) was just kept: its view made (and
        those of a resumed run's stored keyframes) -> its pyramid as points, finest first."""
        current, levels = keyframes[-1], len(self.config.verify_iters)
        check_pyramid_fits(levels, current.depth.shape[0], current.depth.shape[1])
        self.views.update(keyframes, intrinsics)
        return source_pyramid(current.color, current.depth, intrinsics, levels)

    def warm_up(self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor) -> bool:
        """Once, before the first search with compiled kernels: the newest of `keyframes`
        (`sources`: its pyramid, from `kept`) verified against itself from one start and from the
        grid of starts, its result dropped, so that the verification's iterations compile at this
        run's sizes now, not at the first candidate in the middle of the run. Under `process` the
        mapping process compiles its own copies: with loops on the cabinet its longest item took
        22.9 s against 14.2 s without (a60276b). -> whether it ran (the first call only)."""
        if self._warmed:
            return False
        self._warmed = True
        identity = torch.eye(4, dtype=torch.float64)
        for starts in (identity, grid_around(identity, self.config.appearance_offset_m)):
            starts = starts.to(sources[0].points.device)
            verify(
                sources, self.views, keyframes[-1], starts, intrinsics, self.config, self.tracking, kernels=self.kernels
            )
        return True

    def odometry(
        self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor
    ) -> Verification:
        """The newest keyframe (`sources`) at the relative pose the estimates give it from the one
        before: the normal equations there, one linearisation at the finest level, judged as a
        verification is (the estimates are tracking's and mapping's; this only weighs them)."""
        return self._to_previous(keyframes, sources, intrinsics, ODOMETRY_SCHEDULE)

    def step_from_previous(
        self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor
    ) -> Verification:
        """The newest of `keyframes` (`sources`), a frame tracking lost against the map, aligned
        to the keyframe before it over the whole verification schedule, from the estimates'
        relative pose and a 3 x 3 grid around it (`grid_around`, `appearance_offset_m`): its step
        from that keyframe measured against the keyframe's own image. On the cabinet's revisit
        (160x120) the lost frames' steps from the estimates alone passed 19-42 cm wrong; from the
        grid's best they are 4-7 cm off, and the frames' loops then confirm one another."""
        grid = self.config.appearance_offset_m
        return self._to_previous(keyframes, sources, intrinsics, self.config.verify_iters, grid)

    def _to_previous(
        self,
        keyframes: list[Keyframe],
        sources: list[SourcePoints],
        intrinsics: torch.Tensor,
        schedule: tuple[int, ...],
        grid_m: float = 0.0,
    ) -> Verification:
        """The newest keyframe aligned to the one before over `schedule`, from the estimates'
        relative pose (and `grid_around` it, `grid_m` apart, where that is not 0)."""
        previous, current = keyframes[-2], keyframes[-1]
        estimates = relative_pose(previous, current)
        starts = (grid_around(estimates, grid_m) if grid_m else estimates).to(sources[0].points.device)
        config, tracking = self.config, self.tracking
        return verify(sources, self.views, previous, starts, intrinsics, config, tracking, schedule, self.kernels)

    def detect(
        self,
        keyframes: list[Keyframe],
        sources: list[SourcePoints],
        intrinsics: torch.Tensor,
        pixels: torch.Tensor,
        lost: bool = False,
    ) -> LoopDetection:
        """The loops of the newest keyframe (`sources`; `pixels`: flat indices of its sampled
        valid depth, for the candidates' overlap; `lost`: a frame tracking lost), confirmed by
        one another or by the loops the searches before verified (`detect_loops`); its own
        verified loops kept for the next."""
        detection = detect_loops(
            keyframes,
            self.views,
            sources,
            intrinsics,
            pixels,
            self.config,
            self.tracking,
            self.sightings,
            self.kernels,
            lost,
        )
        self._recent.append(detection.sightings(keyframes))
        return detection
