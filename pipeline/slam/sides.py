"""How SLAM's two sides are built from a config, wherever they run (one process or two): each
part takes the config sections it needs."""

from __future__ import annotations

import torch

from pipeline.config import Config, switched_on
from pipeline.render import Renderer, make_capacity_renderer, make_views_renderer
from pipeline.slam.kernels import SlamKernels, make_kernels
from pipeline.slam.loops.closer import LoopCloser, NoLoopCloser
from pipeline.slam.mapping.backend import BackendSettings
from pipeline.slam.mapping.captured import CapturedMapping
from pipeline.slam.mapping.window import MapSettings
from pipeline.slam.tracking.trackers import Tracker, TrackSettings, make_tracker


def kernels_for(config: Config, device: torch.device) -> SlamKernels:
    """SLAM's kernels, compiled when `run.compile` says so (the grid's: and `run.compile_grid`;
    the align iterations ahead of time: and `run.precompile`)."""
    compiled = switched_on(config.run.compile, device.type == "cuda")
    return make_kernels(compiled, config.run.compile_grid, config.run.precompile)


def tracker_for(config: Config, renderer: Renderer, device: torch.device) -> Tracker:
    """The configured tracker, its kernels compiled when `run.compile` says so."""
    cuda = device.type == "cuda"
    kernels = kernels_for(config, device)
    near, far = config.render.near, config.render.far
    capacity_renderer = make_capacity_renderer(config.render, config.gaussians, device)
    return make_tracker(
        TrackSettings(renderer, config.tracking, config.loss, near, far, kernels, cuda, capacity_renderer)
    )


def backend_settings(config: Config, renderer: Renderer, device: torch.device) -> BackendSettings:
    """What the mapping side needs besides the map and its loop closer: renderers, losses,
    kernels, the graphed passes where `mapping.graph` asks for them and a fixed-capacity
    renderer exists, and its config sections."""
    cuda = device.type == "cuda"
    kernels = kernels_for(config, device)
    views = make_views_renderer(config.render, config.gaussians, device)
    near, far = config.render.near, config.render.far
    capacity_renderer = make_capacity_renderer(config.render, config.gaussians, device)
    captured = None
    if capacity_renderer is not None and switched_on(config.mapping.graph, cuda):
        captured = CapturedMapping(capacity_renderer, config.mapping, config.loss, kernels, near, far, device)
    window = MapSettings(renderer, views, config.mapping, config.loss, near, far, kernels, captured)
    return BackendSettings(window, config.keyframes, config.densify, config.gaussians, config.run.seed)


def loop_closer_for(config: Config, settings: BackendSettings) -> LoopCloser | NoLoopCloser:
    """A fresh loop closer when `loops.enabled` (its alignment iterating with the mapping side's
    kernels: `settings`), else one that does nothing."""
    if not config.loops.enabled:
        return NoLoopCloser()
    kernels = settings.window.kernels.align
    return LoopCloser(config.loops, config.tracking, config.keyframes.overlap_samples, config.run.seed, kernels)
