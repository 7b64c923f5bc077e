"""The trajectory: every frame tracked, with its pose, the keyframe it follows, its pose as
tracked, its time and how tracking judged it.

A frame's pose follows the keyframe it was tracked after (its anchor: the newest keyframe of the
map version it was tracked against), as ORB-SLAM's frames follow their reference keyframe: when
mapping refines that keyframe or a loop corrects it, `poses_with` moves the frame along. The
poses as tracked (before any such correction) are kept beside them.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import Enum

import torch

from pipeline.geometry import invert_pose
from pipeline.slam.keyframes import KeyframePose
from pipeline.slam.state import FrontendState


class TrackingState(Enum):
    """How a frame's pose came about."""

    TRACKED = "tracked"  # from the prediction, judged sound
    RELOCALISED = "relocalised"  # judged lost from the prediction, sound from a keyframe's pose
    LOST = "lost"  # judged lost: the pose is kept but not trusted (nor mapped)


class Trajectory:
    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.poses: list[torch.Tensor] = []  # [4, 4] camera-to-world per frame tracked (since a resume: as saved)
        self.tracked: list[torch.Tensor] = []  # [4, 4] camera-to-world per frame as tracked (before any correction)
        self.anchors: list[KeyframePose | None] = []  # per frame: the keyframe it follows, with its pose then
        self.timestamps: list[float | None] = []  # seconds, per frame tracked (None: before a resume)
        self.states: list[TrackingState] = []  # per frame tracked
        self.last_good = -1  # position in `poses` of the last frame not lost
        self.last_prior: torch.Tensor | None = None  # [4, 4] the device's camera-to-world at `last_good`

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def lost_in_row(self) -> int:
        """Frames judged lost since the last one that was not."""
        return len(self.states) - 1 - self.last_good

    def append(
        self,
        c2w: torch.Tensor,
        anchor: KeyframePose | None,
        timestamp: float,
        state: TrackingState,
        prior: torch.Tensor | None,
    ) -> None:
        """A frame tracked: its pose `c2w` [4, 4] camera-to-world (on the device), the keyframe it
        follows, its time (seconds), how it was judged and the device's pose `prior` [4, 4] (None:
        the frames bring none)."""
        self.poses.append(c2w)
        self.tracked.append(c2w)
        self.anchors.append(anchor)
        self.timestamps.append(timestamp)
        self.states.append(state)
        if state is not TrackingState.LOST:
            self.last_good = len(self.poses) - 1
            self.last_prior = prior

    def poses_with(self, keyframes: Sequence[KeyframePose], frames: int | None = None) -> list[torch.Tensor]:
        """The first `frames` poses (default: all) as the mapping side's `keyframes` now place
        them: a keyframe's own pose as mapping refined or a loop corrected it; any other frame
        follows its anchor, pose = anchor_now @ inv(anchor_then) @ pose. An anchor whose pose is
        the very tensor it was leaves the pose as it is (no rounding)."""
        now = {k.position: k.c2w for k in keyframes}
        corrections: dict[int, torch.Tensor] = {}  # id(anchor) -> its correction, made once
        return [self.followed(position, now, corrections) for position in range(len(self.poses))[:frames]]

    def followed(
        self, position: int, now: dict[int, torch.Tensor], known: dict[int, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """One frame's pose as the keyframes' poses `now` (position -> [4, 4]) place it
        (`poses_with`; `known`: the anchors' corrections made so far)."""
        if position in now:
            return now[position].to(self.device)
        correction = self._correction(self.anchors[position], now, {} if known is None else known)
        pose = self.poses[position]
        return pose if correction is None else correction @ pose

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

    def follow(self, keyframes: Sequence[KeyframePose]) -> None:
        """After a resume: each saved frame follows the newest of `keyframes` (the restored map's)
        at or before it, from its pose as saved."""
        ordered = sorted(keyframes, key=lambda k: k.position)
        newest: KeyframePose | None = None
        for position in range(len(self.poses)):
            while ordered and ordered[0].position <= position:
                newest = ordered.pop(0)
            self.anchors[position] = newest

    def state(
        self, frames: int, prior: torch.Tensor | None, keyframes: Sequence[KeyframePose], loss_history: list[float]
    ) -> FrontendState:
        """A host copy of the first `frames` frames, their poses as the mapping side's `keyframes`
        place them (`poses_with`), with `prior` [4, 4] (the device's pose at the last good frame
        by then) and tracking's `loss_history` by then."""
        return FrontendState(
            poses=torch.stack(self.poses_with(keyframes, frames)).cpu() if frames else torch.zeros(0, 4, 4),
            loss_history=loss_history,
            last_prior=None if prior is None else prior.cpu(),
            lost_frames=self._frames_in(TrackingState.LOST, frames),
            relocalised_frames=self._frames_in(TrackingState.RELOCALISED, frames),
            tracked_poses=torch.stack(self.tracked[:frames]).cpu() if frames else torch.zeros(0, 4, 4),
        )

    def _frames_in(self, state: TrackingState, frames: int) -> list[int]:
        """Positions of the first `frames` poses whose tracking ended in `state`."""
        return [i for i, s in enumerate(self.states[:frames]) if s is state]

    @staticmethod
    def restored(saved: FrontendState, device: torch.device) -> Trajectory:
        """The frames of `saved` (their times are not kept: the first frames after it use the
        fixed jump limit and the whole velocity). They follow no keyframe until `follow` names them."""
        frames = saved.frames_done
        trajectory = Trajectory(device)
        trajectory.poses = list(saved.poses.to(device))
        tracked = saved.tracked_poses if saved.tracked_poses is not None else saved.poses
        trajectory.tracked = list(tracked.to(device))
        trajectory.anchors = [None] * frames
        trajectory.timestamps = [None] * frames
        states = dict.fromkeys(range(frames), TrackingState.TRACKED)
        states |= dict.fromkeys(saved.relocalised_frames, TrackingState.RELOCALISED)
        states |= dict.fromkeys(saved.lost_frames, TrackingState.LOST)
        trajectory.states = list(states.values())
        trajectory.last_good = max(set(range(frames)) - set(saved.lost_frames), default=-1)
        trajectory.last_prior = None if saved.last_prior is None else saved.last_prior.to(device)
        return trajectory
