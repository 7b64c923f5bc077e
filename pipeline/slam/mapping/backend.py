"""SLAM's mapping side: densify, select keyframes, optimise the map, publish a map version.

It holds the map, the keyframes and the random state of mapping, and takes tracked frames in
order. A frame whose tracking was judged lost is never mapped; a live session may also skip
frames when mapping falls behind (`skip`): both are passed on with their poses, unmapped.
"""

from __future__ import annotations

import logging
import random
from collections.abc import Callable
from dataclasses import replace

import torch

from pipeline.config import Config
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians, Renderer
from pipeline.slam.gaussian_map import concatenate, copied, gathered, most_opaque, seed_gaussians
from pipeline.slam.handoff import FrameResult, TrackedFrame, TrackerMark
from pipeline.slam.keyframes import Keyframe, most_redundant, select_window
from pipeline.slam.loops.closer import Correction, LoopCloser
from pipeline.slam.loops.detection import ClosedLoop, closed_loop_line
from pipeline.slam.loops.map_correction import move_map
from pipeline.slam.map_version import MapVersion
from pipeline.slam.mapping.densify import densify_mask
from pipeline.slam.mapping.window import MapSettings, WindowPlan, map_window, optimise_window
from pipeline.slam.state import BackendState, LoopState
from pipeline.slam.timing import StageClock

log = logging.getLogger("gsplatam")
MAP_BOUND_MARGIN = 0.9  # a map past mapping.max_gaussians is cut to this fraction of it


def scene_radius_of(depth: torch.Tensor, config: Config) -> float:
    """The scene's radius (metres) from the first frame's depth [H, W]: its largest depth over
    `mapping.scene_radius_divisor` (one host read)."""
    return float(depth.max()) / config.mapping.scene_radius_divisor


class MappingBackend:
    def __init__(self, config: Config, renderer: Renderer, settings: MapSettings, device: torch.device) -> None:
        self.config = config
        self.renderer = renderer
        self.settings = settings
        self.device = device
        self.gaussians: Gaussians | None = None
        self.keyframes: list[Keyframe] = []
        self.scene_radius = 0.0  # metres
        self.rng = random.Random(config.run.seed)  # mapping's view picks
        self.generator = torch.Generator().manual_seed(config.run.seed)  # keyframe overlap samples
        self.frames_seen = 0  # frames passed to this side, mapped or not
        self.last_keyframe_seen = -config.keyframes.every  # frames_seen when the last keyframe was taken
        self.latest: MapVersion | None = None
        self.mark: TrackerMark | None = None  # the tracking side's state as of the last frame seen
        self.intrinsics: torch.Tensor | None = None  # [3, 3] the frames' camera (one per run), once mapped
        self._cycle: list[int] = []  # keyframe indices still to visit in this round of refinement passes
        self.on_step: Callable[[], None] | None = None  # called before every optimiser step (a sign of life)
        self.clock = StageClock(device)
        self.loops: LoopCloser | None = None  # loops.enabled: the keyframe pose graph and loop search
        if config.loops.enabled:
            self.loops = LoopCloser(config.loops, config.tracking, config.keyframes.overlap_samples, config.run.seed)

    def state(self) -> BackendState:
        """A host copy of this side's state (after the last frame it was given)."""
        assert self.gaussians is not None
        return BackendState(
            gaussians=copied(self.gaussians, "cpu"),
            keyframes=[
                replace(k, color_u8=k.color_u8.cpu(), depth=k.depth.cpu(), c2w=k.c2w.cpu()) for k in self.keyframes
            ],
            scene_radius=self.scene_radius,
            rng_state=self.rng.getstate(),
            generator_state=self.generator.get_state(),
            frames_seen=self.frames_seen,
            loops=None if self.loops is None else self._loop_state(),
            intrinsics=None if self.intrinsics is None else self.intrinsics.cpu(),
        )

    def _loop_state(self) -> LoopState:
        """A host copy of loop closure's state, its nodes at the keyframes' current poses."""
        assert self.loops is not None
        state = self.loops.state
        return replace(
            state,
            creator=state.creator.cpu(),
            node_c2w=self.loops.graph_poses(self.keyframes),
            node_positions=list(state.node_positions),
            loops=list(state.loops),
            closed=list(state.closed),
        )

    def restore(self, saved: BackendState, mark: TrackerMark) -> None:
        """Continue from `saved`, the tracking side standing at `mark`; publishes the map."""
        dev = self.device
        self.gaussians = copied(saved.gaussians, dev)
        self.keyframes = [
            replace(k, color_u8=k.color_u8.to(dev), depth=k.depth.to(dev), c2w=k.c2w.to(dev)) for k in saved.keyframes
        ]
        self.scene_radius = saved.scene_radius
        self.rng.setstate(saved.rng_state)
        self.generator.set_state(saved.generator_state)
        every = self.config.keyframes.every
        self.frames_seen = saved.frames_seen
        self.last_keyframe_seen = (saved.frames_seen - 1) // every * every  # the cadence of an unbroken run
        self.mark = mark
        self.latest = None
        self.intrinsics = None if saved.intrinsics is None else saved.intrinsics.to(dev)
        if self.loops is not None:
            self.loops.restore(saved.loops, len(self.gaussians), dev)
        self.publish()

    def map(self, tracked: TrackedFrame, is_last: bool = False) -> FrameResult:
        """Densify, select the window and optimise the map with the tracked frame; publish the
        new version. A frame judged lost is skipped instead."""
        if tracked.result.lost:
            return self.skip(tracked)
        frame, c2w = tracked.frame, tracked.c2w
        self.intrinsics = frame.intrinsics
        if tracked.ready is not None:
            torch.cuda.current_stream().wait_event(tracked.ready)
            for tensor in (frame.color, frame.depth, frame.intrinsics, c2w):
                tensor.record_stream(torch.cuda.current_stream())
        keeps = self.frames_seen - self.last_keyframe_seen >= self.config.keyframes.every or is_last
        with self.clock.stage("densify"):
            if self.gaussians is None:
                added = self._initialise(frame, c2w)
                window: list[Keyframe] = []
            else:
                added = self._densify(frame, c2w)
                window = self._window(frame, c2w)
            if self.loops is not None:
                self.loops.seeded(added, keeps, self.device)
        current = Keyframe.of(frame.index, frame.color, frame.depth, c2w, tracked.mark.poses_done - 1)
        with self.clock.stage("mapping"):
            self._map(window + [current], frame.intrinsics)
        correction = None
        if keeps:
            self._keep(current)
            if self.loops is not None:
                correction = self.loops.keyframe_kept(self.keyframes, frame.intrinsics)
                if correction is not None:
                    self._correct(correction)
        self._bound_map()
        self.publish()
        if correction is not None:
            self._published(correction)
        seconds = self.clock.read()
        return self._passed(tracked, added, seconds.get("densify", 0.0), seconds.get("mapping", 0.0), mapped=True)

    def loops_closed(self) -> list[ClosedLoop]:
        """The loops closed so far, oldest first (none without loop closure)."""
        return [] if self.loops is None else list(self.loops.state.closed)

    def _keep(self, keyframe: Keyframe) -> None:
        """Add a keyframe; past `keyframes.max_kept`, drop the most redundant viewpoint."""
        self.keyframes.append(keyframe)
        self.last_keyframe_seen = self.frames_seen
        limit = self.config.keyframes.max_kept
        if limit and len(self.keyframes) > limit:
            protected = min(self.config.mapping.window, limit - 1)
            del self.keyframes[most_redundant(torch.stack([k.c2w for k in self.keyframes]), protected)]

    def _bound_map(self) -> None:
        """Past `mapping.max_gaussians`, keep the most opaque 90% of it (the margin spares a
        selection every frame)."""
        limit = self.config.mapping.max_gaussians
        if limit and self.gaussians is not None and len(self.gaussians) > limit:
            keep = most_opaque(self.gaussians, int(MAP_BOUND_MARGIN * limit))
            if keep is not None:
                self.gaussians = gathered(self.gaussians, keep)
                if self.loops is not None:
                    self.loops.kept(keep)

    def _correct(self, correction: Correction) -> None:
        """Move the map and the stored keyframes with a closed loop's corrected poses."""
        assert self.gaussians is not None and self.loops is not None
        creator = self.loops.state.creator
        self.gaussians = move_map(self.gaussians, creator, correction.old_c2w, correction.node_c2w)
        node_of = self.loops.state.node_of()
        self.keyframes = [
            replace(k, c2w=correction.node_c2w[node_of[k.pose.position]].to(k.c2w)) for k in self.keyframes
        ]

    def _published(self, correction: Correction) -> None:
        """Record the closed loop, with the time from its detection's start until its corrected
        map was published (`LoopState.closed`)."""
        assert self.loops is not None
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)  # once per loop closed: its times are the GPU's too
        closed = self.loops.published(correction)
        log.info(closed_loop_line(closed))  # a mapping process configures no logging: its client logs the report

    def refine(self, renders: int, should_stop: Callable[[], bool] | None = None, views: int = 0) -> int:
        """A refinement pass: `renders` view renders over `views` stored keyframes (0: as many as
        `mapping.window`) taken from a shuffled cycle through all of them, so that every keyframe
        is revisited; their poses are optimised too (`mapping.refine_pose_lr`; the first keyframe
        stays: it fixes the map's frame). Publishes the result; `should_stop` ends it early (a
        frame waits). -> the renders done (0 before the first frame)."""
        if self.gaussians is None or self.intrinsics is None or renders <= 0:
            return 0
        positions = self._refinement_views(views or self.config.mapping.window)
        chosen = [self.keyframes[p] for p in positions]
        fixed = frozenset(i for i, p in enumerate(positions) if p == 0)
        plan = WindowPlan(renders, should_stop, self.config.mapping.refine_pose_lr, fixed, self.on_step)
        radius = self.scene_radius
        result = optimise_window(self.gaussians, chosen, self.intrinsics, radius, self.rng, self.settings, plan)
        self.gaussians = result.gaussians
        if self.loops is not None:
            self.loops.kept(result.kept)
        for position, c2w in zip(positions, result.c2w):
            self.keyframes[position] = replace(self.keyframes[position], c2w=c2w)
        self.publish()
        return result.renders

    def _refinement_views(self, count: int) -> list[int]:
        """Positions of the next `count` keyframes of the refinement cycle."""
        where = {k.index: i for i, k in enumerate(self.keyframes)}
        wanted = min(count, len(self.keyframes))
        picks: list[int] = []
        while len(picks) < wanted:
            if not self._cycle:
                self._cycle = list(where)
                self.rng.shuffle(self._cycle)
            position = where.get(self._cycle.pop())  # None: dropped from the store since
            if position is not None and position not in picks:
                picks.append(position)
        return picks

    def skip(self, tracked: TrackedFrame) -> FrameResult:
        """Pass a tracked frame on without mapping it."""
        return self._passed(tracked, 0, 0.0, 0.0, mapped=False)

    def _passed(
        self, tracked: TrackedFrame, added: int, densify_s: float, mapping_s: float, mapped: bool
    ) -> FrameResult:
        self.frames_seen += 1
        self.mark = tracked.mark
        result = tracked.result
        result.seconds.update(densify=densify_s, mapping=mapping_s)
        result.seconds["total"] = result.seconds.get("tracking", 0.0) + densify_s + mapping_s
        result.added = added
        result.gaussians = 0 if self.gaussians is None else len(self.gaussians)
        result.mapped = mapped
        result.map_version = 0 if self.latest is None else self.latest.number
        return result

    def publish(self) -> None:
        """Make the current map the latest version tracking reads."""
        assert self.gaussians is not None
        ready = None
        if self.device.type == "cuda":
            ready = torch.cuda.Event()
            ready.record()
        number = 1 if self.latest is None else self.latest.number + 1
        self.latest = MapVersion(number, self.gaussians, ready, tuple(k.pose for k in self.keyframes))

    def _initialise(self, frame: DeviceFrame, c2w: torch.Tensor) -> int:
        """Seed the map from every valid-depth pixel of the first frame; -> Gaussians added."""
        valid = frame.depth > 0
        self.gaussians = seed_gaussians(frame.color, frame.depth, frame.intrinsics, c2w, valid, self.config.gaussians)
        self.scene_radius = scene_radius_of(frame.depth, self.config)
        return len(self.gaussians)

    def _densify(self, frame: DeviceFrame, c2w: torch.Tensor) -> int:
        """Add Gaussians where the map at the tracked pose misses the frame; -> Gaussians added."""
        assert self.gaussians is not None
        render = self.config.render
        camera = Camera(invert_pose(c2w), frame.intrinsics, frame.width, frame.height, render.near, render.far)
        with torch.no_grad():
            out = self.renderer(self.gaussians, camera)
            mask = densify_mask(out.silhouette, out.depth, frame.depth, self.config.densify)
            seeds = seed_gaussians(frame.color, frame.depth, frame.intrinsics, c2w, mask, self.config.gaussians)
        self.gaussians = concatenate(self.gaussians, seeds)
        return len(seeds)

    def _window(self, frame: DeviceFrame, c2w: torch.Tensor) -> list[Keyframe]:
        """The keyframes mapped with the current frame: overlapping ones and the newest."""
        picks = select_window(
            self.keyframes,
            frame.depth,
            frame.intrinsics,
            c2w,
            window=self.config.mapping.window,
            samples=self.config.keyframes.overlap_samples,
            generator=self.generator,
        )
        return [self.keyframes[i] for i in picks]

    def _map(self, views: list[Keyframe], intrinsics: torch.Tensor) -> None:
        assert self.gaussians is not None
        if self.config.mapping.iters == 0:
            return
        radius = self.scene_radius
        result = map_window(self.gaussians, views, intrinsics, radius, self.rng, self.settings, self.on_step)
        self.gaussians = result.gaussians
        if self.loops is not None:
            self.loops.kept(result.kept)
