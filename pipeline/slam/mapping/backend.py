"""SLAM's mapping side: densify, select keyframes, optimise the map, publish a map version.

It holds the map, the keyframes and the random state of mapping, and takes the tracked frames
(`TrackedFrame`) in order; what it did with each comes back as a `MappedFrame`. A frame whose
tracking was judged lost is never mapped: with loop closure on it is searched for a loop
(`_lost`). Loop closure, when on, runs at each keyframe kept (`LoopCloser`; off, a
`NoLoopCloser` that does nothing).
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

from pipeline.config import DensifyConfig, GaussianConfig, KeyframeConfig, MappingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians
from pipeline.slam.gaussian_map import concatenate, copied, gathered, most_opaque, seed_gaussians
from pipeline.slam.handoff import FrameResult, TrackedFrame
from pipeline.slam.keyframes import Keyframe, most_redundant, select_window
from pipeline.slam.loops.closer import LoopCloser, NoLoopCloser
from pipeline.slam.loops.detection import ClosedLoop
from pipeline.slam.map_version import MapVersion
from pipeline.slam.mapping.bundle import adjust, covisible
from pipeline.slam.mapping.densify import densify_mask
from pipeline.slam.mapping.window import MapSettings, WindowPlan, WindowResult, map_window, optimise_window
from pipeline.slam.state import BackendState
from pipeline.slam.timing import StageClock

MAP_BOUND_MARGIN = 0.9  # a map past mapping.max_gaussians is cut to this fraction of it


def scene_radius_of(depth: torch.Tensor, mapping: MappingConfig) -> float:
    """The scene's radius (metres) from the first frame's depth [H, W]: its largest depth over
    `mapping.scene_radius_divisor` (one host read)."""
    return float(depth.max()) / mapping.scene_radius_divisor


@dataclass(frozen=True)
class BackendSettings:
    """What the mapping side is built with besides its loop closer (`sides.backend_settings`)."""

    window: MapSettings  # the window optimisation's: renderers, the mapping section, losses, kernels
    keyframes: KeyframeConfig
    densify: DensifyConfig
    gaussians: GaussianConfig  # the kind of Gaussian seeded
    seed: int  # run.seed: mapping's random state starts from it


@dataclass(frozen=True)
class MappedFrame:
    """What the mapping side did with a frame."""

    mapped: bool  # False: passed on unmapped (tracking judged it lost)
    added: int  # Gaussians densification added
    gaussians: int  # in the map after it
    map_version: int  # the version published after it (the latest one when not mapped)
    densify_s: float  # densification, with keyframe selection
    mapping_s: float
    closed: tuple[ClosedLoop, ...] = ()  # the loop closed at its keyframe, if one was

    def filled(self, result: FrameResult) -> FrameResult:
        """`result`, tracking's fields filled in, with mapping's (the seconds' total too)."""
        result.seconds.update(densify=self.densify_s, mapping=self.mapping_s)
        result.seconds["total"] = result.seconds.get("tracking", 0.0) + self.densify_s + self.mapping_s
        result.added = self.added
        result.gaussians = self.gaussians
        result.mapped = self.mapped
        result.map_version = self.map_version
        return result


class MappingBackend:
    def __init__(self, settings: BackendSettings, loops: LoopCloser | NoLoopCloser, device: torch.device) -> None:
        self.settings = settings
        self.mapping = settings.window.mapping
        self.loops = loops  # the keyframe pose graph and loop search (a NoLoopCloser when loops are off)
        self.device = device
        self.gaussians: Gaussians | None = None
        self.keyframes: list[Keyframe] = []
        self.scene_radius = 0.0  # metres
        self.rng = random.Random(settings.seed)  # mapping's view picks
        self.generator = torch.Generator().manual_seed(settings.seed)  # keyframe overlap samples
        self.frames_seen = 0  # frames passed to this side, mapped or not
        self.last_keyframe_seen = -settings.keyframes.every  # frames_seen when the last keyframe was taken
        self.latest: MapVersion | None = None
        self.intrinsics: torch.Tensor | None = None  # [3, 3] the frames' camera (one per run), once mapped
        self._cycle: list[int] = []  # keyframe indices still to visit in this round of refinement passes
        self._local_turn = False  # the last idle refinement pass took the newest keyframe's covisible window
        self._covisible: tuple[tuple[int, int], list[int]] = ((-1, 0), [])  # (newest index, store size) -> positions
        self.on_step: Callable[[], None] | None = None  # called before every optimiser step (a sign of life)
        self.clock = StageClock(device)

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
            loops=self.loops.saved(self.keyframes),
            intrinsics=None if self.intrinsics is None else self.intrinsics.cpu(),
        )

    def restore(self, saved: BackendState) -> None:
        """Continue from `saved`; publishes the map."""
        dev = self.device
        self.gaussians = copied(saved.gaussians, dev)
        self.keyframes = [
            replace(k, color_u8=k.color_u8.to(dev), depth=k.depth.to(dev), c2w=k.c2w.to(dev)) for k in saved.keyframes
        ]
        self.scene_radius = saved.scene_radius
        self.rng.setstate(saved.rng_state)
        self.generator.set_state(saved.generator_state)
        every = self.settings.keyframes.every
        self.frames_seen = saved.frames_seen
        self.last_keyframe_seen = (saved.frames_seen - 1) // every * every  # the cadence of an unbroken run
        self.latest = None
        self.intrinsics = None if saved.intrinsics is None else saved.intrinsics.to(dev)
        self.loops.restore(saved.loops, len(self.gaussians), dev)
        self.publish()

    def map(self, tracked: TrackedFrame, is_last: bool = False) -> MappedFrame:
        """Densify, select the window and optimise the map with the tracked frame (`is_last`:
        the run's last, kept as a keyframe; so is one the tracking side chose, and every
        `keyframes.every`-th frame given); publish the new version."""
        frame, c2w = tracked.frame, tracked.c2w
        if tracked.ready is not None:
            torch.cuda.current_stream().wait_event(tracked.ready)
            for tensor in (frame.color, frame.depth, frame.intrinsics, c2w):
                tensor.record_stream(torch.cuda.current_stream())
        if tracked.lost:
            return self._lost(tracked)
        self.intrinsics = frame.intrinsics
        keeps = (
            tracked.keyframe or is_last or self.frames_seen - self.last_keyframe_seen >= self.settings.keyframes.every
        )
        with self.clock.stage("densify"):
            if self.gaussians is None:
                added = self._initialise(frame, c2w)
                window: list[Keyframe] = []
            else:
                added = self._densify(frame, c2w)
                window = self._window(frame, c2w)
            self.loops.seeded(added, keeps, self.device)
        current = Keyframe.of(frame.index, frame.color, frame.depth, c2w, tracked.position)
        with self.clock.stage("mapping"):
            self._map(window + [current], frame.intrinsics)
            if keeps:
                self._keep(current)
                self._adjust(frame.intrinsics)
        if keeps:
            assert self.gaussians is not None
            self.gaussians, self.keyframes = self.loops.close_loops(self.gaussians, self.keyframes, frame.intrinsics)
        self._bound_map()
        self.publish()
        closed = self.loops.map_published(self.device)
        seconds = self.clock.read()
        return self._passed(added, seconds.get("densify", 0.0), seconds.get("mapping", 0.0), True, closed)

    def _keep(self, keyframe: Keyframe) -> None:
        """Add a keyframe; past `keyframes.max_kept`, drop the most redundant viewpoint."""
        self.keyframes.append(keyframe)
        self.last_keyframe_seen = self.frames_seen
        limit = self.settings.keyframes.max_kept
        if limit and len(self.keyframes) > limit:
            protected = min(self.mapping.window, limit - 1)
            del self.keyframes[most_redundant(torch.stack([k.c2w for k in self.keyframes]), protected)]

    def _bound_map(self) -> None:
        """Past `mapping.max_gaussians`, keep the most opaque 90% of it (the margin spares a
        selection every frame)."""
        limit = self.mapping.max_gaussians
        if limit and self.gaussians is not None and len(self.gaussians) > limit:
            keep = most_opaque(self.gaussians, int(MAP_BOUND_MARGIN * limit))
            if keep is not None:
                self.gaussians = gathered(self.gaussians, keep)
                self.loops.kept(keep)

    def finish(self, renders: int, should_stop: Callable[[], bool] | None = None) -> int:
        """The run's final refinement (`mapping.final_iters`): `renders` view renders over every
        keyframe, their poses moving at `mapping.final_pose_lr`. -> the renders done."""
        return self.refine(renders, should_stop, len(self.keyframes), self.mapping.final_pose_lr)

    def refine(
        self, renders: int, should_stop: Callable[[], bool] | None = None, views: int = 0, pose_lr: float | None = None
    ) -> int:
        """A refinement pass: `renders` view renders over `views` stored keyframes taken from a
        shuffled cycle through all of them, so that every keyframe is revisited (0: a window of
        at most `mapping.window`, in turn the newest keyframe's covisible window and the next of
        that cycle); their poses are optimised too (at `pose_lr`, default `mapping.refine_pose_lr`;
        the first keyframe stays: it fixes the map's frame). Publishes the result; `should_stop`
        ends it early (a frame waits). -> the renders done (0 before the first frame)."""
        if self.gaussians is None or self.intrinsics is None or renders <= 0:
            return 0
        if views:
            positions = self._refinement_views(views)
        else:
            self._local_turn = not self._local_turn
            positions = self._covisible_views() if self._local_turn else self._refinement_views(self.mapping.window)
        chosen = [self.keyframes[p] for p in positions]
        fixed = frozenset(i for i, p in enumerate(positions) if p == 0)
        pose_lr = self.mapping.refine_pose_lr if pose_lr is None else pose_lr
        plan = WindowPlan(renders, should_stop, pose_lr, fixed, self.on_step)
        radius, window = self.scene_radius, self.settings.window
        result = optimise_window(self.gaussians, chosen, self.intrinsics, radius, self.rng, window, plan)
        self._optimised(positions, result)
        self.publish()
        return result.renders

    def _adjust(self, intrinsics: torch.Tensor) -> None:
        """Local bundle adjustment at the keyframe just kept (`bundle.adjust`): the poses of it
        and of the keyframes that see most of it (`mapping.adjust_window` in all; 0: none) with
        the map, the oldest of them fixed."""
        if self.mapping.adjust_window < 2 or self.gaussians is None:
            return
        samples = self.settings.keyframes.overlap_samples
        positions = covisible(self.keyframes, self.mapping.adjust_window, intrinsics, samples, self.generator)
        if len(positions) < 2:
            return
        views = [self.keyframes[p] for p in positions]
        result = adjust(self.gaussians, views, intrinsics, self.scene_radius, self.rng, self.settings.window)
        self._optimised(positions, result)

    def _optimised(self, positions: list[int], result: WindowResult) -> None:
        """Take a pass over the stored keyframes at `positions`: its map and their poses."""
        self.gaussians = result.gaussians
        self.loops.kept(result.kept)
        for position, c2w in zip(positions, result.c2w):
            self.keyframes[position] = replace(self.keyframes[position], c2w=c2w)

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

    def _covisible_views(self) -> list[int]:
        """Positions of the newest keyframe and of the stored ones that see what it sees
        (`select_window`: at most `mapping.window` in all), chosen once per newest keyframe."""
        assert self.intrinsics is not None
        newest = self.keyframes[-1]
        key = (newest.index, len(self.keyframes))
        if self._covisible[0] != key:
            older = select_window(
                self.keyframes[:-1],
                newest.depth,
                self.intrinsics,
                newest.c2w,
                window=self.mapping.window,
                samples=self.settings.keyframes.overlap_samples,
                generator=self.generator,
            )
            self._covisible = (key, older + [len(self.keyframes) - 1])
        return list(self._covisible[1])

    def refine_between(self, renders: int) -> MappedFrame:
        """Pass on a frame tracked between keyframes (`mapping.rate=keyframe` under the sequential
        schedule: not densified, not mapped) after a refinement pass of `renders` view renders
        over the keyframes (`refine`; 0: none), timed as its mapping."""
        with self.clock.stage("mapping"):
            self.refine(renders)
        return self._passed(0, 0.0, self.clock.read().get("mapping", 0.0), False)

    def _lost(self, tracked: TrackedFrame) -> MappedFrame:
        """A frame tracking judged lost: never densified nor mapped. With loop closure on it is
        searched for a loop (`LoopCloser.frame_lost`); where one is accepted, the frame is kept
        as a keyframe at the pose the loop gives it and the map moves with the correction."""
        frame = tracked.frame
        if self.gaussians is None or not self.keyframes or not self.loops.searches_lost_frames:
            return self._passed(0, 0.0, 0.0, False)
        with self.clock.stage("mapping"):
            lost = Keyframe.of(frame.index, frame.color, frame.depth, tracked.c2w, tracked.position)
            found = self.loops.frame_lost(self.gaussians, self.keyframes, lost, frame.intrinsics)
            if found is not None:
                self.gaussians, store = found
                self.keyframes = store[:-1]
                self._keep(store[-1])
        if found is not None:
            self.publish()
        closed = self.loops.map_published(self.device)
        return self._passed(0, 0.0, self.clock.read().get("mapping", 0.0), False, closed)

    def _passed(
        self, added: int, densify_s: float, mapping_s: float, mapped: bool, closed: tuple[ClosedLoop, ...] = ()
    ) -> MappedFrame:
        self.frames_seen += 1
        gaussians = 0 if self.gaussians is None else len(self.gaussians)
        version = 0 if self.latest is None else self.latest.number
        return MappedFrame(mapped, added, gaussians, version, densify_s, mapping_s, closed)

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
        self.gaussians = seed_gaussians(frame.color, frame.depth, frame.intrinsics, c2w, valid, self.settings.gaussians)
        self.scene_radius = scene_radius_of(frame.depth, self.mapping)
        return len(self.gaussians)

    def _densify(self, frame: DeviceFrame, c2w: torch.Tensor) -> int:
        """Add Gaussians where the map at the tracked pose misses the frame; -> Gaussians added."""
        assert self.gaussians is not None
        window = self.settings.window
        camera = Camera(invert_pose(c2w), frame.intrinsics, frame.width, frame.height, window.near, window.far)
        with torch.no_grad():
            out = window.renderer(self.gaussians, camera)
            mask = densify_mask(out.silhouette, out.depth, frame.depth, self.settings.densify)
            seeds = seed_gaussians(frame.color, frame.depth, frame.intrinsics, c2w, mask, self.settings.gaussians)
        self.gaussians = concatenate(self.gaussians, seeds)
        return len(seeds)

    def _window(self, frame: DeviceFrame, c2w: torch.Tensor) -> list[Keyframe]:
        """The keyframes mapped with the current frame: overlapping ones and the newest."""
        picks = select_window(
            self.keyframes,
            frame.depth,
            frame.intrinsics,
            c2w,
            window=self.mapping.window,
            samples=self.settings.keyframes.overlap_samples,
            generator=self.generator,
        )
        return [self.keyframes[i] for i in picks]

    def _map(self, views: list[Keyframe], intrinsics: torch.Tensor) -> None:
        assert self.gaussians is not None
        if self.mapping.iters == 0:
            return
        radius, window = self.scene_radius, self.settings.window
        result = map_window(self.gaussians, views, intrinsics, radius, self.rng, window, self.on_step)
        self.gaussians = result.gaussians
        self.loops.kept(result.kept)
