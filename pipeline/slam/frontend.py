"""SLAM's tracking side: predict the pose, track it against a published map version, judge it.

It holds what tracking carries from frame to frame (the estimated poses, the loss history that
lost-tracking detection compares against, the last device pose) and hands each frame to mapping
as a `TrackedFrame`, with the marks a checkpoint cut at that frame needs from this side.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from pipeline.config import TrackingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import constant_velocity, invert_pose
from pipeline.slam.map_version import MapVersion
from pipeline.slam.results import FrameResult
from pipeline.slam.timing import StageClock
from pipeline.slam.tracking import Tracker

LOSS_EXPLOSION_FACTOR = 10.0  # x the median per-pixel tracking loss of earlier frames
LOSS_HISTORY_MIN = 5


@dataclass(frozen=True)
class TrackerMark:
    """The tracking side's state just after one frame: a checkpoint cut there takes the first
    `poses_done` poses and `losses_done` loss-history entries, and that frame's device pose."""

    poses_done: int
    losses_done: int
    prior: torch.Tensor | None  # [4, 4] camera-to-world


@dataclass
class TrackedFrame:
    """What tracking hands to mapping."""

    frame: DeviceFrame
    c2w: torch.Tensor  # [4, 4] estimated camera-to-world, on the device
    result: FrameResult  # the tracking fields filled in; mapping fills the rest
    mark: TrackerMark
    ready: torch.cuda.Event | None  # recorded after tracking on its stream; None on the CPU


class TrackingFrontend:
    def __init__(self, tracker: Tracker, config: TrackingConfig, device: torch.device) -> None:
        self.tracker = tracker
        self.config = config
        self.device = device
        self.poses: list[torch.Tensor] = []  # [4, 4] camera-to-world per frame tracked
        self.loss_history: list[float] = []
        self.last_prior: torch.Tensor | None = None
        self.clock = StageClock(device)

    @property
    def frames_done(self) -> int:
        return len(self.poses)

    def track(self, frame: DeviceFrame, latest: MapVersion | None) -> TrackedFrame:
        """Frame t against the latest map version (None: the first frame, where the map starts:
        its pose is the identity). Reads the frame's tracking scalars once, to judge it."""
        started = time.perf_counter()
        with self.clock.stage("tracking"):
            failure = ""
            if latest is None:
                c2w = c2w_init = torch.eye(4, device=self.device)
                loss, coverage = torch.zeros((), device=self.device), torch.ones((), device=self.device)
            else:
                c2w_init = self._initial_pose(frame)
                tracked = self.tracker(latest.for_current_stream(), frame, c2w_init)
                c2w, loss, coverage = tracked.c2w.detach(), tracked.best_loss, tracked.coverage
                failure = tracked.failure
            self.poses.append(c2w)
            self.last_prior = frame.c2w_prior
        ready = None
        if frame.depth.is_cuda:
            ready = torch.cuda.Event()
            ready.record()
        result = self._judge(frame, c2w, c2w_init, loss, coverage, failure)
        result.seconds["tracking"] = self.clock.read().get("tracking", 0.0)
        if frame.received_at is not None:
            result.received_at = frame.received_at
            result.age_at_start_s = started - frame.received_at
        mark = TrackerMark(len(self.poses), len(self.loss_history), self.last_prior)
        return TrackedFrame(frame, c2w, result, mark, ready)

    def _initial_pose(self, frame: DeviceFrame) -> torch.Tensor:
        """The device's own motion since the last frame applied to the last estimate when the
        frame brings a pose prior, else constant velocity."""
        poses, prior = self.poses, self.last_prior
        if frame.c2w_prior is not None and prior is not None:
            return poses[-1] @ invert_pose(prior) @ frame.c2w_prior
        return poses[-1] if len(poses) < 2 else constant_velocity(poses[-2], poses[-1])

    def _judge(
        self,
        frame: DeviceFrame,
        c2w: torch.Tensor,
        c2w_init: torch.Tensor,
        loss: torch.Tensor,
        coverage: torch.Tensor,
        failure: str,
    ) -> FrameResult:
        """Read the frame's device scalars once and judge whether tracking held (`failure`: the
        tracking method's own verdict, e.g. the alignment's solve)."""
        valid = float((frame.depth > 0).sum())
        cov = float(coverage)
        per_pixel = float(loss) / max(cov * valid, 1.0)
        jump = float(torch.linalg.norm(c2w[:3, 3] - c2w_init[:3, 3]))
        history, tracked = self.loss_history, self.frames_done > 1
        lost, warning = "", ""
        if not math.isfinite(per_pixel) and tracked:
            lost = "tracking loss is not finite"
        elif failure:
            lost = failure
        elif jump > self.config.lost_translation_m:
            lost = f"pose jumped {jump:.3f} m from its prediction"
        elif (
            len(history) >= LOSS_HISTORY_MIN and per_pixel > LOSS_EXPLOSION_FACTOR * sorted(history)[len(history) // 2]
        ):
            lost = f"tracking loss {per_pixel:.4f} per pixel is over {LOSS_EXPLOSION_FACTOR:g}x its running median"
        elif tracked and cov < self.config.lost_coverage:
            # Entering unmapped space looks like this too: the frame is mapped, so the map can grow there.
            warning = f"map covers only {cov:.0%} of the valid pixels"
        if tracked and math.isfinite(per_pixel):
            history.append(per_pixel)
        return FrameResult(
            index=frame.index,
            timestamp=frame.timestamp,
            c2w=c2w.cpu(),
            seconds={},
            gaussians=0,
            added=0,
            tracking_loss=per_pixel,
            coverage=cov,
            lost=lost,
            warning=warning,
            c2w_gt=None if frame.c2w_gt is None else frame.c2w_gt.cpu(),
        )
