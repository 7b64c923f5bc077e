"""SplaTAM: a tracking side and a mapping side, run one frame at a time (the sequential
schedule): `step` runs a frame through both sides in order, and `checkpoint()` is the map of
the last frame mapping has passed, with the poses and tracking state up to that frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import torch

from pipeline.config import Config
from pipeline.frame import DeviceFrame
from pipeline.render import Gaussians, Renderer
from pipeline.slam.handoff import FrameResult
from pipeline.slam.keyframes import KeyframePose, chooser_for
from pipeline.slam.mapping.backend import MappingBackend
from pipeline.slam.sides import backend_settings, loop_closer_for, tracker_for
from pipeline.slam.state import Checkpoint
from pipeline.slam.tracking.frontend import TrackerMark, TrackingFrontend

WARM_UP_FRAMES = 2  # the first frame runs mapping only, the second tracking too


class SplaTAM:
    def __init__(self, config: Config, renderer: Renderer, device: torch.device) -> None:
        self.config = config
        self.renderer = renderer
        self.device = device
        self._tracker = tracker_for(config, renderer, device)
        self._backend_settings = backend_settings(config, renderer, device)
        self._start_afresh()

    def _start_afresh(self) -> None:
        """Empty tracking and mapping sides around the same tracker and mapping settings, whose
        compiled kernels and recorded CUDA graphs are kept."""
        self.frontend = TrackingFrontend(self._tracker, self.config.tracking, self.device)
        loops = loop_closer_for(self.config, self._backend_settings)
        self.backend = MappingBackend(self._backend_settings, loops, self.device)
        self.chooser = chooser_for(self.config)  # None: every frame mapped
        self._passed_mark: TrackerMark | None = None  # the tracking side's state as of the last frame mapping passed

    @property
    def frames_done(self) -> int:
        """Frames mapping has passed (the frames a checkpoint holds)."""
        return 0 if self._passed_mark is None else self._passed_mark.poses_done

    @property
    def gaussians(self) -> Gaussians | None:
        """The latest published map (None before the first frame)."""
        latest = self.backend.latest
        return None if latest is None else latest.gaussians

    @property
    def poses(self) -> list[torch.Tensor]:
        """[4, 4] camera-to-world of every frame mapping has passed."""
        return self.frontend.trajectory.poses_with([k.pose for k in self.backend.keyframes], self.frames_done)

    def step(self, frame: DeviceFrame, is_last: bool = False) -> FrameResult:
        """Track one frame (colour, depth and intrinsics on the device) and map it, unless
        tracking judged it lost (then, with loops on, only searched for a loop) (at
        `mapping.rate=keyframe`: unless it is no keyframe; then a short refinement pass over the
        keyframes, `mapping.refine_between` renders)."""
        tracked, result = self.frontend.track(frame, self.backend.latest)
        if result.lost:
            mapped = self.backend.map(tracked)
        elif self.chooser is None:
            mapped = self.backend.map(tracked, is_last)
        else:
            why = self.chooser.reason(frame, tracked.c2w, tracked.position, result.coverage, is_last)
            result.between_keyframes = not why
            if why:
                self.chooser.kept(KeyframePose(frame.index, tracked.c2w, tracked.position))
                mapped = self.backend.map(replace(tracked, keyframe=True), is_last)
            else:
                mapped = self.backend.refine_between(self.config.mapping.refine_between)
        self._passed_mark = self.frontend.mark()
        return mapped.filled(result)

    def finish(self, final_renders: int, should_stop: Callable[[], bool] | None = None) -> int:
        """After the last frame: `final_renders` view renders of refinement over every keyframe
        (`mapping.final_iters`; their poses at `mapping.final_pose_lr`), ending at its next step
        once `should_stop()`; published. ->
        the renders done."""
        return self.backend.finish(final_renders, should_stop)

    @property
    def failure(self) -> str:
        """Mapping runs in the caller's thread here: a failure is raised where it happens."""
        return ""

    def unmapped(self) -> list[int]:
        return []

    def stop_waiting(self) -> None:
        """Nothing is waited for here: every state is complete."""

    def sample_kernels(self, step: str) -> float:
        """No other process launches this SLAM's kernels (`KernelSampler`)."""
        return 0.0

    def mapping_summary(self) -> dict[str, Any] | None:
        """Mapping runs on the frame clock here: frames.csv says what it did per frame."""
        return None

    def close(self) -> None:
        """Nothing runs beside the caller's threads: nothing to stop."""

    def warm_up(self, frame: DeviceFrame) -> None:
        """Map `frame` and track it against that map, as the first two frames of a scratch run,
        then start afresh, as if nothing had run. On CUDA the first mapping and the first
        tracking compile their kernels and record their graphs (seconds, bench/NOTES.md); a
        live session warms up on a frame it then drops, so that the camera does not move on
        for seconds between its first frames. Only before the first frame."""
        if self.frontend.frames_done:
            raise RuntimeError("SplaTAM.warm_up runs before the first frame only")
        for index in range(WARM_UP_FRAMES):
            self.step(replace(frame, index=index))
        self._start_afresh()

    def checkpoint(self) -> Checkpoint:
        """A host copy of everything needed to continue the run after the last frame mapped."""
        keyframes = [k.pose for k in self.backend.keyframes]
        return Checkpoint(self.frontend.state(self._passed_mark, keyframes), self.backend.state())

    def restore(self, saved: Checkpoint) -> None:
        """Continue from `saved` (the state of the run after `saved.frames_done` frames)."""
        self.frontend.restore(saved.tracking)
        self.backend.restore(saved.mapping)
        self._passed_mark = self.frontend.mark()
        keyframes = [k.pose for k in self.backend.keyframes]
        self.frontend.trajectory.follow(keyframes)
        if self.chooser is not None:
            self.chooser.resumed(keyframes)
