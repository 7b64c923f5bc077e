"""SplaTAM, one frame at a time: track, densify, select keyframes, map."""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

import torch

from pipeline.config import Config
from pipeline.frame import DeviceFrame
from pipeline.geometry import constant_velocity, invert_pose
from pipeline.render import Camera, Renderer
from pipeline.slam.densify import densify_mask
from pipeline.slam.gaussian_map import concatenate, copied, detached, seed_gaussians
from pipeline.slam.kernels import make_kernels
from pipeline.slam.keyframes import Keyframe, select_window
from pipeline.slam.mapping import MapSettings, map_window
from pipeline.slam.state import Checkpoint, SlamState
from pipeline.slam.timing import StageClock
from pipeline.slam.tracking import TrackResult, TrackSettings, make_tracker

LOSS_EXPLOSION_FACTOR = 10.0  # x the median per-pixel tracking loss of earlier frames
LOSS_HISTORY_MIN = 5


@dataclass
class FrameResult:
    index: int
    timestamp: float
    c2w: torch.Tensor  # [4, 4] estimated camera-to-world, on the host
    seconds: dict[str, float]  # tracking, densify (with keyframe selection), mapping, total
    gaussians: int
    added: int
    tracking_loss: float  # per tracked pixel at the chosen pose (adam: its loss; align: squared point-to-plane, m^2)
    coverage: float  # fraction of valid-depth pixels used by tracking
    lost: str = ""  # empty when tracking looked healthy, else why not
    c2w_gt: torch.Tensor | None = None  # [4, 4] the frame's reference camera-to-world, on the host


@dataclass(frozen=True)
class TrackingVerdict:
    """Tracking's outcome for one frame, read on the host right after tracking."""

    lost: str  # empty when tracking held, else why not
    loss: float  # per tracked pixel at the chosen pose
    coverage: float  # fraction of valid-depth pixels tracked


class SplaTAM:
    def __init__(self, config: Config, renderer: Renderer, device: torch.device) -> None:
        self.config = config
        self.renderer = renderer
        self.device = device
        self.state = SlamState()
        self.rng = random.Random(config.run.seed)
        self.generator = torch.Generator().manual_seed(config.run.seed)
        self.clock = StageClock(device)
        compiled = config.run.compile == "on" or (config.run.compile == "auto" and device.type == "cuda")
        kernels = make_kernels(compiled)
        near, far = config.render.near, config.render.far
        self.tracker = make_tracker(TrackSettings(renderer, config.tracking, config.loss, near, far, kernels))
        self.map_settings = MapSettings(renderer, config.mapping, config.loss, near, far, kernels)

    @property
    def frames_done(self) -> int:
        return len(self.state.poses)

    def step(self, frame: DeviceFrame, is_last: bool = False) -> FrameResult:
        """Process one frame (colour, depth and intrinsics on the device) and return its result.

        Tracking is judged as soon as it ends: a lost frame keeps its pose (one per frame) but
        is neither densified, mapped nor kept as a keyframe."""
        cfg, state = self.config, self.state
        with self.clock.stage("total"):
            added, window = 0, []
            if state.gaussians is None:
                c2w = torch.eye(4, device=self.device)
                verdict = TrackingVerdict(lost="", loss=0.0, coverage=1.0)
                with self.clock.stage("densify"):
                    added = self._initialise(frame, c2w)
            else:
                with self.clock.stage("tracking"):
                    c2w_init = self._initial_pose(frame)
                    tracked = self.tracker(detached(state.gaussians), frame, c2w_init)
                    c2w = tracked.c2w
                verdict = self._judge(frame, tracked, c2w_init)
                if not verdict.lost:
                    with self.clock.stage("densify"):
                        added = self._densify(frame, c2w)
                        window = self._window(frame, c2w)
            if not verdict.lost:
                current = Keyframe.of(frame.index, frame.color, frame.depth, c2w.detach())
                with self.clock.stage("mapping"):
                    self._map(window + [current], frame.intrinsics)
                if self.frames_done % cfg.keyframes.every == 0 or is_last:
                    state.keyframes.append(current)
            state.poses.append(c2w.detach())
            state.last_prior = frame.c2w_prior
        return self._result(frame, c2w, verdict, self.clock.read(), added)

    def _initialise(self, frame: DeviceFrame, c2w: torch.Tensor) -> int:
        """Seed the map from every valid-depth pixel of the first frame; -> Gaussians added."""
        valid = frame.depth > 0
        self.state.gaussians = seed_gaussians(
            frame.color, frame.depth, frame.intrinsics, c2w, valid, self.config.gaussians
        )
        self.state.scene_radius = float(frame.depth.max()) / self.config.mapping.scene_radius_divisor
        return len(self.state.gaussians)

    def _initial_pose(self, frame: DeviceFrame) -> torch.Tensor:
        """The device's own motion since the last frame applied to the last estimate when the
        frame brings a pose prior, else constant velocity."""
        poses, prior = self.state.poses, self.state.last_prior
        if frame.c2w_prior is not None and prior is not None:
            return poses[-1] @ invert_pose(prior) @ frame.c2w_prior
        return poses[-1] if len(poses) < 2 else constant_velocity(poses[-2], poses[-1])

    def _densify(self, frame: DeviceFrame, c2w: torch.Tensor) -> int:
        """Add Gaussians where the map at the tracked pose misses the frame; -> Gaussians added."""
        state, render = self.state, self.config.render
        assert state.gaussians is not None
        camera = Camera(invert_pose(c2w), frame.intrinsics, frame.width, frame.height, render.near, render.far)
        with torch.no_grad():
            out = self.renderer(state.gaussians, camera)
            mask = densify_mask(out.silhouette, out.depth, frame.depth, self.config.densify)
            seeds = seed_gaussians(frame.color, frame.depth, frame.intrinsics, c2w, mask, self.config.gaussians)
        state.gaussians = concatenate(state.gaussians, seeds)
        return len(seeds)

    def _window(self, frame: DeviceFrame, c2w: torch.Tensor) -> list[Keyframe]:
        """The keyframes mapped with the current frame: overlapping ones and the newest."""
        cfg, keyframes = self.config, self.state.keyframes
        picks = select_window(
            keyframes,
            frame.depth,
            frame.intrinsics,
            c2w,
            window=cfg.mapping.window,
            samples=cfg.keyframes.overlap_samples,
            generator=self.generator,
        )
        return [keyframes[i] for i in picks]

    def _map(self, views: list[Keyframe], intrinsics: torch.Tensor) -> None:
        state = self.state
        assert state.gaussians is not None
        if self.config.mapping.iters == 0:
            return
        state.gaussians = map_window(
            state.gaussians, views, intrinsics, state.scene_radius, self.rng, self.map_settings
        )

    def _judge(self, frame: DeviceFrame, tracked: TrackResult, c2w_init: torch.Tensor) -> TrackingVerdict:
        """Read the tracking's device scalars once and judge whether it held."""
        valid = float((frame.depth > 0).sum())
        cov = float(tracked.coverage)
        per_pixel = float(tracked.best_loss) / max(cov * valid, 1.0)
        jump = float(torch.linalg.norm(tracked.c2w[:3, 3] - c2w_init[:3, 3]))
        history = self.state.loss_history
        lost = ""
        if not math.isfinite(per_pixel):
            lost = "tracking loss is not finite"
        elif tracked.failure:
            lost = tracked.failure
        elif jump > self.config.tracking.lost_translation_m:
            lost = f"pose jumped {jump:.3f} m from its prediction"
        elif cov < self.config.tracking.lost_coverage:
            lost = f"map covers only {cov:.0%} of the valid pixels"
        elif (
            len(history) >= LOSS_HISTORY_MIN and per_pixel > LOSS_EXPLOSION_FACTOR * sorted(history)[len(history) // 2]
        ):
            lost = f"tracking loss {per_pixel:.4g} per pixel is over {LOSS_EXPLOSION_FACTOR:g}x its running median"
        if math.isfinite(per_pixel):
            history.append(per_pixel)
        return TrackingVerdict(lost, per_pixel, cov)

    def _result(
        self, frame: DeviceFrame, c2w: torch.Tensor, verdict: TrackingVerdict, seconds: dict[str, float], added: int
    ) -> FrameResult:
        assert self.state.gaussians is not None
        return FrameResult(
            index=frame.index,
            timestamp=frame.timestamp,
            c2w=c2w.detach().cpu(),
            seconds={k: seconds.get(k, 0.0) for k in ("tracking", "densify", "mapping", "total")},
            gaussians=len(self.state.gaussians),
            added=added,
            tracking_loss=verdict.loss,
            coverage=verdict.coverage,
            lost=verdict.lost,
            c2w_gt=None if frame.c2w_gt is None else frame.c2w_gt.cpu(),
        )

    def checkpoint(self) -> Checkpoint:
        """A host copy of everything needed to continue the run."""
        state = self.state
        assert state.gaussians is not None
        return Checkpoint(
            gaussians=copied(state.gaussians, "cpu"),
            keyframes=[Keyframe(k.index, k.color_u8.cpu(), k.depth.cpu(), k.c2w.cpu()) for k in state.keyframes],
            poses=torch.stack(state.poses).cpu(),
            scene_radius=state.scene_radius,
            loss_history=list(state.loss_history),
            last_prior=None if state.last_prior is None else state.last_prior.cpu(),
            rng_state=self.rng.getstate(),
            generator_state=self.generator.get_state(),
        )

    def restore(self, saved: Checkpoint) -> None:
        """Continue from `saved` (the state of the run after `saved.frames_done` frames)."""
        dev = self.device
        self.state = SlamState(
            gaussians=copied(saved.gaussians, dev),
            keyframes=[Keyframe(k.index, k.color_u8.to(dev), k.depth.to(dev), k.c2w.to(dev)) for k in saved.keyframes],
            poses=list(saved.poses.to(dev)),
            scene_radius=saved.scene_radius,
            loss_history=list(saved.loss_history),
            last_prior=None if saved.last_prior is None else saved.last_prior.to(dev),
        )
        self.rng.setstate(saved.rng_state)
        self.generator.set_state(saved.generator_state)
