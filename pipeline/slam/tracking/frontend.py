"""SLAM's tracking side: predict the pose, track it against a published map version, judge it.

It holds what tracking carries from frame to frame (the estimated poses and which were lost, the
loss history that lost-tracking detection compares against, the last good device pose) and hands
each frame to mapping as a `TrackedFrame`, with the marks a checkpoint cut at that frame needs
from this side.

After a lost frame the next guess comes from the last frame tracked well (never from a lost
pose), and a frame judged lost is tracked again from a few keyframes' poses (`_relocalise`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import Enum

import torch

from pipeline.config import TrackingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import constant_velocity, invert_pose
from pipeline.render import Gaussians
from pipeline.slam.handoff import FrameResult, TrackedFrame, TrackerMark
from pipeline.slam.keyframes import KeyframePose, relocalisation_picks
from pipeline.slam.map_version import MapVersion
from pipeline.slam.state import FrontendState
from pipeline.slam.timing import StageClock
from pipeline.slam.tracking.trackers import Tracker

LOSS_EXPLOSION_FACTOR = 10.0  # x the median per-pixel tracking loss of earlier frames
LOSS_HISTORY_MIN = 5
STALL_RATIO = 0.5  # the next frame this much nearer in time than the last motion took: predict that fraction of it
INTERVAL_WINDOW = 10  # the session's usual frame interval is the median of this many recent ones


class TrackingState(Enum):
    """How a frame's pose came about."""

    TRACKED = "tracked"  # from the prediction, judged sound
    RELOCALISED = "relocalised"  # judged lost from the prediction, sound from a keyframe's pose
    LOST = "lost"  # judged lost: the pose is kept but not trusted (nor mapped)


@dataclass(frozen=True)
class Verdict:
    """A tracked pose judged on the host."""

    per_pixel: float  # the tracking loss per tracked pixel
    coverage: float  # fraction of valid-depth pixels tracked
    lost: str  # why the pose is not to be trusted; empty when it is
    warning: str  # why tracking looks weak though the pose is used (low map coverage)


@dataclass(frozen=True)
class Attempt:
    """One run of the tracker on a frame, judged."""

    c2w: torch.Tensor  # [4, 4] camera-to-world, on the device
    verdict: Verdict
    keyframe: int | None = None  # the frame index of the keyframe it started from (relocalisation)

    @property
    def state(self) -> TrackingState:
        if self.verdict.lost:
            return TrackingState.LOST
        return TrackingState.TRACKED if self.keyframe is None else TrackingState.RELOCALISED


class TrackingFrontend:
    def __init__(self, tracker: Tracker, config: TrackingConfig, device: torch.device) -> None:
        self.tracker = tracker
        self.config = config
        self.device = device
        self.poses: list[torch.Tensor] = []  # [4, 4] camera-to-world per frame tracked (since a resume: as saved)
        self.tracked: list[torch.Tensor] = []  # [4, 4] camera-to-world per frame as tracked (before any correction)
        self.anchors: list[KeyframePose | None] = []  # per frame: the keyframe it follows, with its pose then
        self.timestamps: list[float | None] = []  # seconds, per frame tracked (None: before a resume)
        self.states: list[TrackingState] = []  # per frame tracked
        self.last_good = -1  # position in `poses` of the last frame not lost
        self.loss_history: list[float] = []
        self.last_prior: torch.Tensor | None = None  # [4, 4] the device's camera-to-world at `last_good`
        self.clock = StageClock(device)

    @property
    def frames_done(self) -> int:
        return len(self.poses)

    def poses_with(self, keyframes: Sequence[KeyframePose], frames: int | None = None) -> list[torch.Tensor]:
        """The first `frames` poses (default: all) as the mapping side's `keyframes` now place
        them: a keyframe's own pose as mapping refined or a loop corrected it; any other frame
        follows the keyframe it was tracked after (its anchor: the newest keyframe of the map
        version it was tracked against), pose = anchor_now @ inv(anchor_then) @ pose, as
        ORB-SLAM's frames follow their reference keyframe. An anchor whose pose is the very
        tensor it was leaves the pose as it is (no rounding)."""
        now = {k.position: k.c2w for k in keyframes}
        corrections: dict[int, torch.Tensor] = {}  # id(anchor) -> its correction, made once
        return [self._followed(position, now, corrections) for position in range(len(self.poses))[:frames]]

    def _correction(
        self, anchor: KeyframePose | None, now: dict[int, torch.Tensor], known: dict[int, torch.Tensor]
    ) -> torch.Tensor | None:
        """[4, 4] anchor_now @ inv(anchor_then), or None where the anchor has not moved (or left the store)."""
        if anchor is None or anchor.position not in now or now[anchor.position] is anchor.c2w:
            return None
        if id(anchor) not in known:
            then = anchor.c2w.to(self.device)
            known[id(anchor)] = now[anchor.position].to(then) @ invert_pose(then)
        return known[id(anchor)]

    def _followed(
        self, position: int, now: dict[int, torch.Tensor], known: dict[int, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """One frame's pose as the keyframes' poses `now` (position -> [4, 4]) place it
        (`poses_with`; `known`: the anchors' corrections made so far)."""
        if position in now:
            return now[position].to(self.device)
        correction = self._correction(self.anchors[position], now, {} if known is None else known)
        pose = self.poses[position]
        return pose if correction is None else correction @ pose

    def mark(self) -> TrackerMark:
        """Where this side stands now (a checkpoint cut after the last frame tracked)."""
        return TrackerMark(len(self.poses), len(self.loss_history), self.last_prior)

    def state(self, mark: TrackerMark | None = None, keyframes: Sequence[KeyframePose] = ()) -> FrontendState:
        """A host copy of this side's state as of `mark` (default: now), with the mapping side's
        `keyframes` poses (`poses_with`)."""
        mark = mark or self.mark()
        frames = mark.poses_done
        return FrontendState(
            poses=torch.stack(self.poses_with(keyframes, frames)).cpu() if frames else torch.zeros(0, 4, 4),
            loss_history=list(self.loss_history[: mark.losses_done]),
            last_prior=None if mark.prior is None else mark.prior.cpu(),
            lost_frames=self._frames_in(TrackingState.LOST, frames),
            relocalised_frames=self._frames_in(TrackingState.RELOCALISED, frames),
            tracked_poses=torch.stack(self.tracked[:frames]).cpu() if frames else torch.zeros(0, 4, 4),
        )

    def _frames_in(self, state: TrackingState, frames: int) -> list[int]:
        """Positions of the first `frames` poses whose tracking ended in `state`."""
        return [i for i, s in enumerate(self.states[:frames]) if s is state]

    def restore(self, saved: FrontendState) -> None:
        """Continue after the frames of `saved` (their poses' times are not kept: the first
        frames after it use the fixed jump limit and the whole velocity). Its frames follow no
        keyframe until `follow` names them."""
        frames = saved.frames_done
        self.poses = list(saved.poses.to(self.device))
        tracked = saved.tracked_poses if saved.tracked_poses is not None else saved.poses
        self.tracked = list(tracked.to(self.device))
        self.anchors = [None] * frames
        self.timestamps = [None] * frames
        self.loss_history = list(saved.loss_history)
        states = dict.fromkeys(range(frames), TrackingState.TRACKED)
        states |= dict.fromkeys(saved.relocalised_frames, TrackingState.RELOCALISED)
        states |= dict.fromkeys(saved.lost_frames, TrackingState.LOST)
        self.states = list(states.values())
        self.last_good = max(set(range(frames)) - set(saved.lost_frames), default=-1)
        self.last_prior = None if saved.last_prior is None else saved.last_prior.to(self.device)

    def follow(self, keyframes: Sequence[KeyframePose]) -> None:
        """After a resume: each saved frame follows the newest of `keyframes` (the restored map's)
        at or before it, from its pose as saved."""
        ordered = sorted(keyframes, key=lambda k: k.position)
        newest: KeyframePose | None = None
        for position in range(len(self.poses)):
            while ordered and ordered[0].position <= position:
                newest = ordered.pop(0)
            self.anchors[position] = newest

    def track(self, frame: DeviceFrame, latest: MapVersion | None) -> TrackedFrame:
        """Frame t against the latest map version (None: the first frame, where the map starts:
        its pose is the identity). Reads the frame's tracking scalars once per tracker run, to
        judge it; a lost frame is relocalised (`_relocalise`)."""
        started = time.perf_counter()
        with self.clock.stage("tracking"):
            if latest is None:
                c2w = torch.eye(4, device=self.device)
                zero, one = torch.zeros((), device=self.device), torch.ones((), device=self.device)
                attempt = Attempt(c2w, self._verdict(frame, c2w, c2w, zero, one, "", first=True))
            else:
                gaussians = latest.for_current_stream()
                attempt = self._attempt(gaussians, frame, self._initial_pose(frame, latest.keyframes))
                if attempt.verdict.lost and self.config.relocalise_candidates > 0:
                    attempt = self._relocalise(gaussians, frame, latest.keyframes, attempt)
            self._record(frame, attempt, self._anchor(latest), first=latest is None)
        ready = None
        if frame.depth.is_cuda:
            ready = torch.cuda.Event()
            ready.record()
        result = self._result(frame, attempt)
        result.seconds["tracking"] = self.clock.read().get("tracking", 0.0)
        if frame.received_at is not None:
            result.received_at = frame.received_at
            result.age_at_start_s = started - frame.received_at
        return TrackedFrame(frame, attempt.c2w, result, self.mark(), ready)

    @staticmethod
    def _anchor(latest: MapVersion | None) -> KeyframePose | None:
        """The keyframe a frame tracked against `latest` follows: its newest (the store is oldest
        first). A pose that is a row of the version's stacked poses (the process schedule's
        reader) is copied, so that each frame keeps 16 numbers alive, not the whole stack."""
        if latest is None or not latest.keyframes:
            return None
        newest = latest.keyframes[-1]
        return newest if newest.c2w._base is None else replace(newest, c2w=newest.c2w.clone())

    def _initial_pose(self, frame: DeviceFrame, keyframes: Sequence[KeyframePose]) -> torch.Tensor:
        """From the frames tracked well, never a lost one: the device's own motion since the last
        good frame applied to its estimate when the frames bring pose priors, else constant
        velocity when the last frame was tracked from its prediction and the one before it was
        good too, else the last good pose (after a loss or a relocalisation the velocity starts
        again from zero). Those frames' poses as the map version's `keyframes` place them: after
        a loop's correction the guess moves with the map."""
        good, prior, states, last = self.last_good, self.last_prior, self.states, len(self.poses) - 1
        now = {k.position: k.c2w for k in keyframes}
        if frame.c2w_prior is not None and prior is not None:
            return self._followed(good, now) @ invert_pose(prior) @ frame.c2w_prior
        if good == last >= 1 and states[-1] is TrackingState.TRACKED and states[-2] is not TrackingState.LOST:
            before, latest = self._followed(last - 1, now), self._followed(last, now)
            return constant_velocity(before, latest, self._velocity_fraction(frame))
        return self._followed(good, now)

    def _velocity_fraction(self, frame: DeviceFrame) -> float:
        """The part of the last motion to repeat: all of it, unless the last motion spanned a
        stall (a busy GPU, a reconnection: the live source kept only the newest frame) and the
        next frame is at most STALL_RATIO of that time away; then that fraction."""
        last, before = self.timestamps[-1], self.timestamps[-2]
        if last is None or before is None or last <= before or frame.timestamp <= last:
            return 1.0
        fraction = (frame.timestamp - last) / (last - before)
        return fraction if fraction <= STALL_RATIO else 1.0

    def _jump_limit_m(self, frame: DeviceFrame) -> float:
        """How far a pose may land from its guess and be trusted: `lost_translation_m` per usual
        frame interval, times the intervals since the last good frame (at least one), since after
        a stall or a reconnection the camera has moved on for longer."""
        known = [t for t in self.timestamps[-INTERVAL_WINDOW - 1 :] if t is not None]
        intervals = [b - a for a, b in zip(known, known[1:]) if b > a]
        good = self.timestamps[self.last_good] if self.last_good >= 0 else None
        if not intervals or good is None or frame.timestamp <= good:
            return self.config.lost_translation_m
        usual = sorted(intervals)[len(intervals) // 2]
        return self.config.lost_translation_m * max(1.0, (frame.timestamp - good) / usual)

    def _attempt(
        self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, keyframe: int | None = None
    ) -> Attempt:
        """The configured tracker from camera-to-world `c2w_init` [4, 4], judged (one host read)."""
        tracked = self.tracker(gaussians, frame, c2w_init)
        c2w = tracked.c2w.detach()
        verdict = self._verdict(frame, c2w, c2w_init, tracked.best_loss, tracked.coverage, tracked.failure)
        return Attempt(c2w, verdict, keyframe)

    def _relocalise(
        self, gaussians: Gaussians, frame: DeviceFrame, keyframes: Sequence[KeyframePose], lost: Attempt
    ) -> Attempt:
        """A frame judged lost from the usual guess (the last good pose, or the device's motion
        from it), tracked again from the poses of at most `relocalise_candidates` keyframes,
        spread over the store and a different set on each lost frame in a row
        (`relocalisation_picks`). Of the attempts judged neither lost nor weak (map coverage at
        least `lost_coverage`), the one of least loss per pixel; `lost` if there is none.

        Cost, on lost frames only: up to `relocalise_candidates` more runs of the tracker (each
        as dear as a tracked frame's: adam's `iters` renders and backward passes, align's render
        and solve, and its recovery attempt when the solve fails) and one host read each. A lost
        frame is not mapped, so the extra time replaces mapping's."""
        attempt_in_row = len(self.states) - 1 - self.last_good  # lost frames just before this one
        best = lost
        for position in relocalisation_picks(len(keyframes), self.config.relocalise_candidates, attempt_in_row):
            keyframe = keyframes[position]
            attempt = self._attempt(gaussians, frame, keyframe.c2w, keyframe.index)
            sound = not attempt.verdict.lost and not attempt.verdict.warning
            if sound and (best.verdict.lost or attempt.verdict.per_pixel < best.verdict.per_pixel):
                best = attempt
        return best

    def _verdict(
        self,
        frame: DeviceFrame,
        c2w: torch.Tensor,
        c2w_init: torch.Tensor,
        loss: torch.Tensor,
        coverage: torch.Tensor,
        failure: str,
        first: bool = False,
    ) -> Verdict:
        """Read the tracker's device scalars once and judge whether tracking held (`failure`: the
        tracking method's own verdict, e.g. the alignment's solve; `first`: the map's first frame)."""
        valid = float((frame.depth > 0).sum())
        cov = float(coverage)
        per_pixel = float(loss) / max(cov * valid, 1.0)
        jump = float(torch.linalg.norm(c2w[:3, 3] - c2w_init[:3, 3]))
        history = self.loss_history
        lost, warning = "", ""
        if not math.isfinite(per_pixel) and not first:
            lost = "tracking loss is not finite"
        elif failure:
            lost = failure
        elif not first and jump > (limit := self._jump_limit_m(frame)):
            lost = f"pose jumped {jump:.3f} m from its prediction (at most {limit:.2f} m)"
        elif (
            len(history) >= LOSS_HISTORY_MIN and per_pixel > LOSS_EXPLOSION_FACTOR * sorted(history)[len(history) // 2]
        ):
            lost = f"tracking loss {per_pixel:.4f} per pixel is over {LOSS_EXPLOSION_FACTOR:g}x its running median"
        elif not first and cov < self.config.lost_coverage:
            # Entering unmapped space looks like this too: the frame is mapped, so the map can grow there.
            warning = f"map covers only {cov:.0%} of the valid pixels"
        return Verdict(per_pixel, cov, lost, warning)

    def _record(self, frame: DeviceFrame, attempt: Attempt, anchor: KeyframePose | None, first: bool) -> None:
        """Carry the frame's pose (following `anchor`), and the loss and device pose of a frame
        tracked well, to the next."""
        self.poses.append(attempt.c2w)
        self.tracked.append(attempt.c2w)
        self.anchors.append(anchor)
        self.timestamps.append(frame.timestamp)
        self.states.append(attempt.state)
        if not first and math.isfinite(attempt.verdict.per_pixel):
            self.loss_history.append(attempt.verdict.per_pixel)
        if attempt.state is not TrackingState.LOST:
            self.last_good = len(self.poses) - 1
            self.last_prior = frame.c2w_prior

    def _result(self, frame: DeviceFrame, attempt: Attempt) -> FrameResult:
        verdict = attempt.verdict
        warning = verdict.warning
        if attempt.keyframe is not None:
            warning = f"relocalised from keyframe {attempt.keyframe}"
        return FrameResult(
            index=frame.index,
            timestamp=frame.timestamp,
            c2w=attempt.c2w.cpu(),
            seconds={},
            gaussians=0,
            added=0,
            tracking_loss=verdict.per_pixel,
            coverage=verdict.coverage,
            lost=verdict.lost,
            warning=warning,
            c2w_gt=None if frame.c2w_gt is None else frame.c2w_gt.cpu(),
            relocalised_from=attempt.keyframe,
        )
