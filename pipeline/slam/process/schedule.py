"""SplaTAM with its mapping side in a process of its own (`slam.schedule=process`), or in a
thread of this process on a CUDA stream of its own (`slam.schedule=thread`, mapping_thread.py).

Tracking stays in the pipeline's process: each frame is tracked against the newest complete
map version, and its result is ready at once; the frame then goes to the mapping process
(unless tracking judged it lost), which maps it and, between frames, refines the map over the
keyframes. Frame results therefore carry tracking's fields and the version tracked against;
what mapping did with each frame comes back as `FrameMapped` reports (`mapping_summary`).

At `mapping.rate=keyframe` only keyframes go to mapping: the tracking side chooses them by what
each frame adds (`KeyframeChooser`), and the frames between are tracked only, each following
its keyframe (the last one chosen before it), so that mapping's refinement of that keyframe
moves them too. Offline, tracking then waits only to hand over a keyframe while mapping has not
taken the `slam.max_lead` before it.

The published state observers see (`SlamView`) is every frame tracked so far, the map version
held for the last one and the keyframes' poses as mapping refined them.

A mapping process that fails (dies, hangs, or is no longer waited for after a second signal)
costs no tracked frame: a frame being tracked when it fails completes (not mapped), the next
frame is refused before it is tracked (MappingProcessFailed), and a checkpoint then holds every
frame tracked with the newest complete map version; `failure` says why and `unmapped` which
frames the map lacks.
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import torch

from pipeline.config import Config
from pipeline.errors import MappingProcessFailed
from pipeline.frame import DeviceFrame
from pipeline.render import Gaussians, Renderer, make_renderer
from pipeline.slam.gaussian_map import copied, seed_gaussians
from pipeline.slam.handoff import FrameResult, TrackedFrame
from pipeline.slam.keyframes import KeyframePose, chooser_for
from pipeline.slam.map_version import MapVersion
from pipeline.slam.mapping.backend import scene_radius_of
from pipeline.slam.process.client import MappingProcess
from pipeline.slam.sides import tracker_for
from pipeline.slam.state import BackendState, Checkpoint
from pipeline.slam.tracking.frontend import TrackingFrontend

log = logging.getLogger("gsplatam")

HOLD_AFTER_FAILURE_S = 1.0  # how long the newest version is waited for once the mapping process failed


def start_process_slam(config: Config, device: torch.device, live: bool) -> ProcessSplaTAM:
    """SLAM under the process schedule. The mapping process is started first, so that its
    start-up (an interpreter, torch's and gsplat's imports, CUDA, the renderers) overlaps this
    process's own set-up (the renderer, the tracker). Measured on the H200 (bench/NOTES.md, at
    16f3aff) that did not shorten the warm-up: the mapping process's own start-up is it."""
    mapping = MappingProcess(config, device, live)
    try:
        return ProcessSplaTAM(config, make_renderer(config.render, config.gaussians, device), device, mapping)
    except BaseException:
        mapping.close()
        raise


class ProcessSplaTAM:
    def __init__(self, config: Config, renderer: Renderer, device: torch.device, mapping: MappingProcess) -> None:
        """SLAM over `mapping`, a mapping process started for `config` (`start_process_slam`)."""
        self.config = config
        self.renderer = renderer
        self.device = device
        self._tracker = tracker_for(config, renderer, device)
        self.frontend = TrackingFrontend(self._tracker, config.tracking, device)
        self.chooser = chooser_for(self.config)
        self.mapping = mapping
        self._first_version = 1  # versions from before a warm-up's reset do not count
        self._saved: BackendState | None = None  # the last mapping state received (a checkpoint's)
        self._scene_radius = 0.0  # metres, from the first frame (for a checkpoint without mapping's state)
        self._intrinsics: torch.Tensor | None = None  # [3, 3] on the host, likewise
        self.warms_tracker = device.type == "cuda"  # the tracker's first call compiles and records (seconds)
        self.tracker_warm_up_s: float | None = None  # how long that first call took, overlapped with mapping's start

    @property
    def frames_done(self) -> int:
        """Frames tracked (each is in every checkpoint; mapping may not have reached the last)."""
        return self.frontend.frames_done

    @property
    def held(self) -> MapVersion | None:
        """The map version held for the last frame (None before the first was published)."""
        return self.mapping.reader.held

    @property
    def gaussians(self) -> Gaussians | None:
        held = self.held
        return None if held is None else held.gaussians

    @property
    def poses(self) -> list[torch.Tensor]:
        """[4, 4] camera-to-world per frame tracked, the keyframes' as mapping refined them."""
        return self.frontend.trajectory.poses_with(self._keyframes())

    def _keyframes(self) -> tuple[KeyframePose, ...]:
        held = self.held
        return () if held is None else held.keyframes

    @property
    def failure(self) -> str:
        """Why the mapping process failed (empty while it works, and after a stop the user asked for)."""
        return self.mapping.failure

    def unmapped(self) -> list[int]:
        """The frames handed to mapping that it never took (it ended first)."""
        return self.mapping.unmapped()

    def stop_waiting(self) -> None:
        """Wait for the mapping process no more: what is complete is used (a second signal)."""
        self.mapping.stop_waiting()

    def step(self, frame: DeviceFrame, is_last: bool = False) -> FrameResult:
        """Track `frame` against the newest map version (the first frame starts the map at the
        identity), then hand it to the mapping process unless it is lost (at keyframe rate:
        unless it is lost or no keyframe; a lost frame goes, to be searched for a loop, when
        loops are on). The first frame's step ends once its map is
        published, so the frame taken after that wait is the newest (live), as under the
        sequential schedule. MappingProcessFailed before tracking, never after."""
        self.mapping.check()
        first = self.frontend.frames_done == 0
        caught_up = self.mapping.caught_up()  # before the hold: the version held then holds every keyframe
        latest = None if first else self.mapping.hold_newest(self._first_version)
        anchor = None if self.chooser is None else self.chooser.last
        tracked, result = self.frontend.track(frame, latest, anchor)
        if first:
            self._scene_radius = scene_radius_of(frame.depth, self.config.mapping)
            self._intrinsics = frame.intrinsics.cpu()
        try:
            if result.lost and self.config.loops.enabled:
                self.mapping.hand_over(frame, tracked.c2w, tracked.position, is_last, lost=True)
            result.mapped = not result.lost and self._hand_over(tracked, result, is_last, caught_up)
            if first and result.mapped:
                self._warm_tracker(frame)
                self.mapping.hold_newest(self._first_version)
        except MappingProcessFailed:  # the frame is tracked and kept; the next one is refused
            result.mapped = False
        result.map_version = 0 if latest is None else latest.number
        result.gaussians = 0 if latest is None else len(latest.gaussians)
        result.seconds.update(densify=0.0, mapping=0.0)
        result.seconds["total"] = result.seconds["tracking"]
        return result

    def _warm_tracker(self, frame: DeviceFrame) -> None:
        """While the mapping process starts and maps the first frame, track `frame` against a
        map seeded from itself and drop the result: the tracker's first call (on CUDA its
        compiles and graph recordings) then overlaps mapping's start instead of following it
        at the second frame (`warms_tracker`)."""
        if not self.warms_tracker:
            return
        started = time.perf_counter()
        identity = torch.eye(4, device=self.device)
        valid = frame.depth > 0
        seeds = seed_gaussians(frame.color, frame.depth, frame.intrinsics, identity, valid, self.config.gaussians)
        self.frontend.tracker(seeds, frame, identity)
        self.tracker_warm_up_s = time.perf_counter() - started

    def _hand_over(self, tracked: TrackedFrame, result: FrameResult, is_last: bool, caught_up: bool) -> bool:
        """Hand a frame tracked well to mapping: every one at frame rate; at keyframe rate a
        keyframe only (`KeyframeChooser`: the map's coverage counts only where the version
        tracked against holds every keyframe, `caught_up`), the others marked as between
        keyframes. -> whether mapping got it."""
        frame, c2w, position = tracked.frame, tracked.c2w, tracked.position
        if self.chooser is None:
            return self.mapping.hand_over(frame, c2w, position, is_last)
        why = self.chooser.reason(frame, c2w, position, result.coverage if caught_up else None, is_last)
        result.between_keyframes = not why
        if not why or not self.mapping.hand_over(frame, c2w, position, is_last, keyframe=True):
            return False
        log.debug("frame %d is a keyframe: %s", frame.index, why)
        self.chooser.kept(KeyframePose(frame.index, c2w, position))
        return True

    def warm_up(self, frame: DeviceFrame) -> None:
        """Map `frame` and track it against that map (compiling both processes' kernels), then
        start afresh on both sides. Only before the first frame."""
        if self.frontend.frames_done:
            raise RuntimeError("ProcessSplaTAM.warm_up runs before the first frame only")
        for index in range(2):  # the second is the last of these two: a keyframe at either rate
            self.step(replace(frame, index=index), is_last=index == 1)
        self.mapping.start_afresh()  # after mapping the second frame too
        self._first_version = self.mapping.newest_version() + 1
        self.mapping.reader.release()
        self.frontend = TrackingFrontend(self._tracker, self.config.tracking, self.device)
        self.chooser = chooser_for(self.config)

    def checkpoint(self) -> Checkpoint:
        """Every frame tracked, with mapping's state as of now (a round trip to the mapping
        process). If that process has failed (or fails meanwhile, or is no longer waited for),
        or has sent no state although a version is held: the newest complete map version and
        the mapping state of the last checkpoint (or an empty keyframe store), so that nothing
        tracked is lost."""
        try:
            state = self.mapping.state()[0]
        except MappingProcessFailed:
            state = None
            self.mapping.reader.hold(HOLD_AFTER_FAILURE_S)  # the newest version the process completed
        if state is not None:
            self._saved = state
        mapping = state or self._mapping_from_held()
        if mapping is None:
            raise RuntimeError("no map yet: nothing to checkpoint")
        return Checkpoint(self.frontend.state(keyframes=[k.pose for k in mapping.keyframes]), mapping)

    def _mapping_from_held(self) -> BackendState | None:
        held = self.held
        if held is None:
            return None
        saved = self._saved
        mapped = sum(report.mapped for report in self.mapping.mapped)
        if saved is None:
            rng, generator = random.Random(self.config.run.seed), torch.Generator().manual_seed(self.config.run.seed)
            return BackendState(
                copied(held.gaussians, "cpu"), [], self._scene_radius, rng.getstate(), generator.get_state(), mapped,
                intrinsics=self._intrinsics,
            )  # fmt: skip
        return replace(saved, gaussians=copied(held.gaussians, "cpu"), frames_seen=max(saved.frames_seen, mapped))

    def restore(self, saved: Checkpoint) -> None:
        self.frontend.restore(saved.tracking)
        self.mapping.restore(saved.mapping)
        self._saved = saved.mapping
        self._scene_radius = saved.mapping.scene_radius
        self._intrinsics = saved.mapping.intrinsics
        self._first_version = self.mapping.newest_version()
        keyframes = self.mapping.hold_newest(self._first_version).keyframes
        self.frontend.trajectory.follow(keyframes)
        if self.chooser is not None:
            self.chooser.resumed(keyframes)

    def finish(self, final_renders: int, should_stop: Callable[[], bool] | None = None) -> int:
        """Let mapping take every frame handed to it, then refine (`final_renders` view renders
        over every keyframe, ending at its next step once `should_stop()`); hold the final
        version. -> the final renders done (0 where the mapping process failed: `failure`)."""
        try:
            renders = self.mapping.finish(final_renders, should_stop)
        except MappingProcessFailed as exc:
            log.debug("no final mapping: %s", exc)
            return 0
        newest = self.mapping.newest_version()
        if newest >= self._first_version:  # none after a warm-up when no frame followed it
            self.mapping.hold_newest(newest)
        return renders

    def sample_kernels(self, step: str) -> float:
        """Kernel recording in the mapping process (`KernelSampler`); a mapping thread's kernels
        are in this process's own recording (CUPTI records a process's every stream): none apart."""
        return 0.0 if self.mapping.in_thread else self.mapping.sample_kernels(step)

    def mapping_summary(self) -> dict[str, Any]:
        """What the mapping process did: frames mapped and passed over, their mean times, and the
        refinement passes between frames."""
        reports = self.mapping.mapped
        mapped = [r for r in reports if r.mapped]

        def mean_ms(values: list[float]) -> float | None:
            return 1000 * sum(values) / len(values) if values else None

        return {
            "rate": "keyframe" if self.chooser is not None else "frame",
            "frames_mapped": len(mapped),
            "frames_passed_over": len(reports) - len(mapped),
            "densify_ms": mean_ms([r.densify_s for r in mapped[2:]]),  # as timing_summary: frames 0 and 1 left out
            "mapping_ms": mean_ms([r.mapping_s for r in mapped[2:]]),
            "refinement_renders": self.mapping.refinement_renders,
            "refinement_s": self.mapping.refinement_s,
            "start_up": self._start_up(),
        }

    def _start_up(self) -> dict[str, float | None]:
        """Seconds of the run's start: the mapping process's interpreter and imports, its set-up,
        its first frame mapped (compiles, graph recordings), and the tracker's first call made
        meanwhile (`_warm_tracker`); None where it did not happen."""
        started = self.mapping.started_up
        first = next((report for report in self.mapping.mapped if report.mapped), None)
        return {
            "interpreter_s": None if started is None else started.interpreter_s,
            "setup_s": None if started is None else started.setup_s,
            "first_frame_s": None if first is None else first.densify_s + first.mapping_s,
            "tracker_s": self.tracker_warm_up_s,
        }

    def close(self) -> None:
        self.mapping.close()
