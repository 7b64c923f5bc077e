"""SLAM's tracking side: predict the pose, track it against a published map version, judge it.

It carries the trajectory (`Trajectory`: the poses, what they follow, how they were judged) and
the loss history that lost-tracking detection compares against from frame to frame, and hands
each frame to mapping as a `TrackedFrame`; `mark` says where a checkpoint cut after it stands.

After a lost frame the next guesses come from the last frame tracked well (never from a lost
pose): its pose, and its velocity carried over the time since; a frame judged lost is tracked
again from a few keyframes' poses (`_relocalise`), and taken from there only where the camera
may have moved in the time since (`_reachable`). Visual odometry (the frame's `motion` since the
frame before, from image features) gives a second guess; where it and the usual one disagree,
the frame is tracked from both and the better kept (`_guesses`). Where alignment fails from
every guess, a frame odometry placed takes odometry's pose (`_settle`); a frame still lost keeps
its prediction as its pose, not the failed solve's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch

from pipeline.config import TrackingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import constant_velocity, invert_pose, motion_extent
from pipeline.render import Gaussians
from pipeline.slam.handoff import FrameResult, TrackedFrame
from pipeline.slam.keyframes import KeyframePose, relocalisation_picks
from pipeline.slam.map_version import MapVersion
from pipeline.slam.state import FrontendState
from pipeline.slam.timing import StageClock
from pipeline.slam.tracking.align_tracker import SolveReport, is_large_step
from pipeline.slam.tracking.trackers import Tracker
from pipeline.slam.tracking.trajectory import TrackingState, Trajectory

LOSS_EXPLOSION_FACTOR = 10.0  # x the median per-pixel tracking loss of earlier frames
LOSS_HISTORY_MIN = 5
STALL_RATIO = 0.5  # the next frame this much nearer in time than the last motion took: predict that fraction of it
INTERVAL_WINDOW = 10  # the session's usual frame interval is the median of this many recent ones


@dataclass(frozen=True)
class TrackerMark:
    """The tracking side's state just after one frame: a checkpoint cut there takes the first
    `poses_done` poses (and states) and `losses_done` loss-history entries, and the device
    pose of the last frame tracked well by then."""

    poses_done: int
    losses_done: int
    prior: torch.Tensor | None  # [4, 4] camera-to-world


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
    by_odometry: bool = False  # the pose is odometry's: alignment failed from every guess
    c2w_host: torch.Tensor | None = None  # [4, 4] the same pose on the host, read with the verdict (None: not read)
    solve: SolveReport | None = None  # align: the statistics of the solve it took (or that failed, by_odometry)

    @property
    def state(self) -> TrackingState:
        if self.verdict.lost:
            return TrackingState.LOST
        return TrackingState.TRACKED if self.keyframe is None else TrackingState.RELOCALISED


class TrackingOutcome(NamedTuple):
    """A frame tracked: what mapping takes (unless the frame is lost) and its result so far."""

    tracked: TrackedFrame
    result: FrameResult  # tracking's fields filled in; mapping fills the rest


class TrackingFrontend:
    def __init__(self, tracker: Tracker, config: TrackingConfig, device: torch.device) -> None:
        self.tracker = tracker
        self.config = config
        self.device = device
        self.trajectory = Trajectory(device)
        self.loss_history: list[float] = []
        self.clock = StageClock(device)
        self._last_c2w: torch.Tensor | None = None  # [4, 4] the last frame's pose on the host (as tracked)
        self._large_step = False  # the last frame moved far from the one before, or was lost
        self._last_index: int | None = None  # the frame index of the last frame tracked

    @property
    def frames_done(self) -> int:
        return len(self.trajectory)

    def mark(self) -> TrackerMark:
        """Where this side stands now (a checkpoint cut after the last frame tracked)."""
        return TrackerMark(len(self.trajectory), len(self.loss_history), self.trajectory.last_prior)

    def state(self, mark: TrackerMark | None = None, keyframes: Sequence[KeyframePose] = ()) -> FrontendState:
        """A host copy of this side's state as of `mark` (default: now), with the mapping side's
        `keyframes` poses (`Trajectory.poses_with`)."""
        mark = mark or self.mark()
        history = list(self.loss_history[: mark.losses_done])
        return self.trajectory.state(mark.poses_done, mark.prior, keyframes, history)

    def restore(self, saved: FrontendState) -> None:
        """Continue after the frames of `saved` (`Trajectory.restored`), the next frame expected
        far from its guess as it would have been without the stop (`_note_step` of the last step)."""
        self.trajectory = Trajectory.restored(saved, self.device)
        self.loss_history = list(saved.loss_history)
        self._last_c2w, self._large_step = None, False
        for position in range(max(saved.frames_done - 2, 0), saved.frames_done):  # the last step, as tracked
            self._note_step(self.trajectory.tracked[position].cpu(), self.trajectory.states[position])
        self._last_index = None  # frame indices are not saved: odometry's first step after it is not used

    def track(
        self, frame: DeviceFrame, latest: MapVersion | None, anchor: KeyframePose | None = None
    ) -> TrackingOutcome:
        """Frame t against the latest map version (None: the first frame, where the map starts:
        its pose is the identity). Reads the frame's tracking scalars once per tracker run, to
        judge it; a lost frame is relocalised (`_relocalise`). The frame's pose follows `anchor`
        (None: the newest keyframe of `latest`)."""
        started = time.perf_counter()
        with self.clock.stage("tracking"):
            if latest is None:
                c2w = torch.eye(4, device=self.device)
                zero, one = torch.zeros((), device=self.device), torch.ones((), device=self.device)
                verdict, c2w_host = self._verdict(frame, c2w, c2w, zero, one, "", first=True)
                attempt = Attempt(c2w, verdict, c2w_host=c2w_host)
            else:
                gaussians = latest.for_current_stream()
                guesses, odometry = self._guesses(frame, latest.keyframes)
                attempt = self._best_of(gaussians, frame, guesses)
                if attempt.verdict.lost and self.config.relocalise_candidates > 0:
                    attempt = self._relocalise(gaussians, frame, latest.keyframes, attempt, odometry)
                attempt = self._settle(attempt, guesses[0], odometry)
            self._record(frame, attempt, anchor or self._anchor(latest), first=latest is None)
        ready = None
        if frame.depth.is_cuda:
            ready = torch.cuda.Event()
            ready.record()
        result = self._result(frame, attempt)
        self._note_step(result.c2w, attempt.state)
        self._last_index = frame.index
        result.seconds["tracking"] = self.clock.read().get("tracking", 0.0)
        if frame.received_at is not None:
            result.received_at = frame.received_at
            result.age_at_start_s = started - frame.received_at
        tracked = TrackedFrame(frame, attempt.c2w, len(self.trajectory) - 1, ready, lost=bool(result.lost))
        return TrackingOutcome(tracked, result)

    @staticmethod
    def _anchor(latest: MapVersion | None) -> KeyframePose | None:
        """The keyframe a frame tracked against `latest` follows: its newest (the store is oldest
        first). A pose that is a row of the version's stacked poses (the process schedule's
        reader) is copied, so that each frame keeps 16 numbers alive, not the whole stack."""
        if latest is None or not latest.keyframes:
            return None
        newest = latest.keyframes[-1]
        return newest if newest.c2w._base is None else replace(newest, c2w=newest.c2w.clone())

    def _guesses(
        self, frame: DeviceFrame, keyframes: Sequence[KeyframePose]
    ) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """-> (the poses [4, 4] to track the frame from, odometry's guess or None). The poses: the
        usual guess (`_initial_pose`), and odometry's (`_odometry_guess`) where the frame has
        one: odometry's alone where the two agree (`odometry_agree_m`, `_deg`), else both,
        odometry's first."""
        now = {k.position: k.c2w for k in keyframes}
        usual = self._initial_pose(frame, now)
        odometry = self._odometry_guess(frame, now)
        if odometry is None:
            carried = self._carried_velocity(frame, now)
            return ([usual] if carried is None else [carried, usual]), None
        apart_m, apart_deg = motion_extent(invert_pose(usual) @ odometry).tolist()
        if apart_m <= self.config.odometry_agree_m and apart_deg <= self.config.odometry_agree_deg:
            return [odometry], odometry
        return [odometry, usual], odometry

    def _carried_velocity(self, frame: DeviceFrame, now: dict[int, torch.Tensor]) -> torch.Tensor | None:
        """After lost frames, the camera's last known velocity carried over the time since: the
        motion between the last good frame and the one before it (both tracked, in a row),
        repeated for as many of its intervals as have passed (`constant_velocity`); None
        elsewhere, or where the times do not tell. On fast steady motion (a real loop round a
        cabinet, 17 cm a frame) the last good pose alone is a frame or more behind."""
        trajectory = self.trajectory
        good, states = trajectory.last_good, trajectory.states
        if trajectory.lost_in_row == 0 or good < 1 or states[good] is not TrackingState.TRACKED:
            return None
        intervals = self._intervals_after(good, frame) if states[good - 1] is not TrackingState.LOST else None
        if intervals is None:
            return None
        return constant_velocity(trajectory.followed(good - 1, now), trajectory.followed(good, now), intervals)

    @staticmethod
    def _settle(attempt: Attempt, prediction: torch.Tensor, odometry: torch.Tensor | None) -> Attempt:
        """A frame that alignment lost from every guess: odometry's pose where the frame has one
        (a measurement of the motion, from features matched in the image and in depth: on fast
        real motion it holds where alignment's basin does not; the frame is mapped, as a weak one
        is), else the `prediction` [4, 4] (the first guess) as its pose, since a failed solve's
        pose (one that stopped short, jumped, or fits few pixels) is further off than the guess
        it left."""
        verdict = attempt.verdict
        if not verdict.lost:
            return attempt
        if odometry is None:
            return replace(attempt, c2w=prediction, c2w_host=None)
        warning = f"pose from visual odometry alone (alignment: {verdict.lost})"
        return Attempt(odometry, replace(verdict, lost="", warning=warning), by_odometry=True, solve=attempt.solve)

    def _odometry_guess(self, frame: DeviceFrame, now: dict[int, torch.Tensor]) -> torch.Tensor | None:
        """The last frame's pose moved by odometry's motion since it, as the keyframes now place
        it; None without odometry, where the motion is from another frame, or where the last
        frame was lost (its pose is not to be built on; a frame that odometry placed is never
        lost, see `_settle`)."""
        motion, last = frame.motion, len(self.trajectory) - 1
        if self.config.odometry == "off" or motion is None or motion.since != self._last_index:
            return None
        if last < 0 or self.trajectory.last_good != last:
            return None
        c2c = torch.from_numpy(motion.c2c).to(self.device, torch.float32)
        return self.trajectory.followed(last, now) @ c2c

    def _best_of(self, gaussians: Gaussians, frame: DeviceFrame, guesses: list[torch.Tensor]) -> Attempt:
        """The frame tracked from each guess; of those judged sound (not lost, no warning), the
        one of least loss per pixel, else the first not lost, else the first."""
        attempts = [self._attempt(gaussians, frame, guess, large_step=self._large_step) for guess in guesses]
        sound = [a for a in attempts if not a.verdict.lost and not a.verdict.warning]
        if sound:
            return min(sound, key=lambda a: a.verdict.per_pixel)
        kept = [a for a in attempts if not a.verdict.lost]
        return kept[0] if kept else attempts[0]

    def _initial_pose(self, frame: DeviceFrame, now: dict[int, torch.Tensor]) -> torch.Tensor:
        """From the frames tracked well, never a lost one: the device's own motion since the last
        good frame applied to its estimate when the frames bring pose priors, else constant
        velocity when the last frame was tracked from its prediction and the one before it was
        good too, else the last good pose (after a loss or a relocalisation the velocity starts
        again from zero). Those frames' poses as the map version's keyframes place them (`now`:
        their poses by position): after a loop's correction the guess moves with the map."""
        trajectory = self.trajectory
        good, prior, states, last = trajectory.last_good, trajectory.last_prior, trajectory.states, len(trajectory) - 1
        if frame.c2w_prior is not None and prior is not None:
            return trajectory.followed(good, now) @ invert_pose(prior) @ frame.c2w_prior
        if good == last >= 1 and states[-1] is TrackingState.TRACKED and states[-2] is not TrackingState.LOST:
            before, latest = trajectory.followed(last - 1, now), trajectory.followed(last, now)
            return constant_velocity(before, latest, self._velocity_fraction(frame))
        return trajectory.followed(good, now)

    def _velocity_fraction(self, frame: DeviceFrame) -> float:
        """The part of the last motion to repeat: all of it, unless the last motion spanned a
        stall (a busy GPU, a reconnection: the live source kept only the newest frame) and the
        next frame is at most STALL_RATIO of that time away; then that fraction."""
        fraction = self._intervals_after(len(self.trajectory) - 1, frame)
        return fraction if fraction is not None and fraction <= STALL_RATIO else 1.0

    def _intervals_after(self, position: int, frame: DeviceFrame) -> float | None:
        """The time from the frame at `position` (>= 1) to `frame`, in units of the motion into
        that frame (from the one before it); None where the times do not tell (unknown, or not
        increasing)."""
        before, at = self.trajectory.timestamps[position - 1], self.trajectory.timestamps[position]
        if before is None or at is None or not before < at < frame.timestamp:
            return None
        return (frame.timestamp - at) / (at - before)

    def _jump_limit_m(self, frame: DeviceFrame) -> float:
        """How far a pose may land from its guess and be trusted: `lost_translation_m` per usual
        frame interval, times the intervals since the last good frame (at least one), since after
        a stall or a reconnection the camera has moved on for longer."""
        return self.config.lost_translation_m * max(1.0, self._intervals_since_good(frame) or 1.0)

    def _reach_m(self, frame: DeviceFrame) -> float:
        """How far from the last good pose the camera may be now: `_jump_limit_m`, where the
        frames' times tell; unbounded where they do not (a stream whose time went back, a
        recording replayed or another session, may be anywhere)."""
        intervals = self._intervals_since_good(frame)
        return math.inf if intervals is None else self.config.lost_translation_m * max(1.0, intervals)

    def _intervals_since_good(self, frame: DeviceFrame) -> float | None:
        """The time from the last good frame to this one in usual frame intervals (the median of
        the last INTERVAL_WINDOW); None where the times do not tell."""
        timestamps, last_good = self.trajectory.timestamps, self.trajectory.last_good
        known = [t for t in timestamps[-INTERVAL_WINDOW - 1 :] if t is not None]
        intervals = [b - a for a, b in zip(known, known[1:]) if b > a]
        good = timestamps[last_good] if last_good >= 0 else None
        if not intervals or good is None or frame.timestamp <= good:
            return None
        return (frame.timestamp - good) / sorted(intervals)[len(intervals) // 2]

    def _note_step(self, c2w: torch.Tensor, state: TrackingState) -> None:
        """Whether the next frame is expected far from its guess: the frame just tracked (its
        pose `c2w` [4, 4] on the host) moved more than `align_large_step_m` or `_deg` from the
        one before (constant velocity repeats that step), or was lost (the next guess is then
        an older pose)."""
        if self._last_c2w is not None:
            moved_m, moved_deg = motion_extent(invert_pose(self._last_c2w) @ c2w).tolist()
            self._large_step = is_large_step(moved_m, moved_deg, self.config) or state is TrackingState.LOST
        self._last_c2w = c2w

    def _attempt(
        self,
        gaussians: Gaussians,
        frame: DeviceFrame,
        c2w_init: torch.Tensor,
        keyframe: int | None = None,
        large_step: bool = False,
    ) -> Attempt:
        """The configured tracker from camera-to-world `c2w_init` [4, 4], judged (one host read)."""
        tracked = self.tracker(gaussians, frame, c2w_init, large_step=large_step)
        c2w = tracked.c2w.detach()
        verdict, c2w_host = self._verdict(frame, c2w, c2w_init, tracked.best_loss, tracked.coverage, tracked.failure)
        return Attempt(c2w, verdict, keyframe, c2w_host=c2w_host, solve=tracked.solve)

    def _relocalise(
        self,
        gaussians: Gaussians,
        frame: DeviceFrame,
        keyframes: Sequence[KeyframePose],
        lost: Attempt,
        odometry: torch.Tensor | None,
    ) -> Attempt:
        """A frame judged lost from the usual guess (the last good pose, or the device's motion
        from it), tracked again from the poses of at most `relocalise_candidates` keyframes,
        spread over the store and a different set on each lost frame in a row
        (`relocalisation_picks`). Of the attempts judged neither lost nor weak (map coverage at
        least `lost_coverage`), the one of least loss per pixel; `lost` if there is none. An
        attempt further than the camera may have moved (`_reachable`) is a look-alike place,
        not taken: on a real loop round a cabinet, relocalisation from the first keyframe took
        frames 1-1.5 m from where they were, and every later frame followed.

        Cost, on lost frames only: up to `relocalise_candidates` more runs of the tracker (each
        as dear as a tracked frame's: adam's `iters` renders and backward passes, align's render
        and solve, and its recovery attempt when the solve fails) and one host read each. A lost
        frame is not mapped, so the extra time replaces mapping's."""
        best = lost
        now = {k.position: k.c2w for k in keyframes}
        picks = relocalisation_picks(len(keyframes), self.config.relocalise_candidates, self.trajectory.lost_in_row)
        for position in picks:
            keyframe = keyframes[position]
            attempt = self._attempt(gaussians, frame, keyframe.c2w, keyframe.index, large_step=True)
            sound = not attempt.verdict.lost and not attempt.verdict.warning
            sound = sound and self._reachable(frame, attempt.c2w, odometry, now)
            if sound and (best.verdict.lost or attempt.verdict.per_pixel < best.verdict.per_pixel):
                best = attempt
        return best

    def _reachable(
        self, frame: DeviceFrame, c2w: torch.Tensor, odometry: torch.Tensor | None, now: dict[int, torch.Tensor]
    ) -> bool:
        """Whether the camera may be at `c2w` [4, 4]: within `lost_translation_m` of odometry's
        guess where the frame has one (odometry measured the motion, however long it took),
        else within `_reach_m` of the last good pose (as the keyframes `now` place it)."""
        if odometry is not None:
            origin, reach = odometry, self.config.lost_translation_m
        else:
            reach = self._reach_m(frame)
            if math.isinf(reach):
                return True
            origin = self.trajectory.followed(self.trajectory.last_good, now)
        return float(torch.linalg.norm(c2w[:3, 3] - origin[:3, 3])) <= reach

    def _verdict(
        self,
        frame: DeviceFrame,
        c2w: torch.Tensor,
        c2w_init: torch.Tensor,
        loss: torch.Tensor,
        coverage: torch.Tensor,
        failure: str,
        first: bool = False,
    ) -> tuple[Verdict, torch.Tensor]:
        """Read the tracker's device scalars and the pose `c2w` [4, 4] in one transfer (each read
        waits for the GPU's queue) and judge whether tracking held (`failure`: the tracking
        method's own verdict, e.g. the alignment's solve; `first`: the map's first frame) -> the
        verdict and `c2w` on the host."""
        jump_m = torch.linalg.norm(c2w[:3, 3] - c2w_init[:3, 3])
        scalars = torch.stack([(frame.depth > 0).sum().double(), coverage.double(), loss.double(), jump_m.double()])
        read = torch.cat([scalars, c2w.reshape(-1).double()]).cpu()
        valid, cov, raw_loss, jump = read[:4].tolist()
        c2w_host = read[4:].reshape(4, 4).to(c2w.dtype)
        per_pixel = raw_loss / max(cov * valid, 1.0)
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
        return Verdict(per_pixel, cov, lost, warning), c2w_host

    def _record(self, frame: DeviceFrame, attempt: Attempt, anchor: KeyframePose | None, first: bool) -> None:
        """Carry the frame's pose (following `anchor`), and the loss and device pose of a frame
        tracked well, to the next."""
        self.trajectory.append(attempt.c2w, anchor, frame.timestamp, attempt.state, frame.c2w_prior)
        if not first and not attempt.by_odometry and math.isfinite(attempt.verdict.per_pixel):
            self.loss_history.append(attempt.verdict.per_pixel)

    def _result(self, frame: DeviceFrame, attempt: Attempt) -> FrameResult:
        verdict = attempt.verdict
        warning = verdict.warning
        if attempt.keyframe is not None:
            warning = f"relocalised from keyframe {attempt.keyframe}"
        return FrameResult(
            index=frame.index,
            timestamp=frame.timestamp,
            c2w=attempt.c2w.cpu() if attempt.c2w_host is None else attempt.c2w_host,
            seconds={},
            gaussians=0,
            added=0,
            tracking_loss=verdict.per_pixel,
            coverage=verdict.coverage,
            lost=verdict.lost,
            warning=warning,
            c2w_gt=None if frame.c2w_gt is None else frame.c2w_gt.cpu(),
            relocalised_from=attempt.keyframe,
            solve=attempt.solve,
        )
