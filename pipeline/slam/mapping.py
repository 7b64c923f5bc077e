"""Mapping: optimise the Gaussians against a window of keyframes with their poses fixed."""

from __future__ import annotations

import random
from dataclasses import dataclass

import torch

from pipeline.config import LossConfig, MappingConfig
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians, Renderer, ViewsRenderer
from pipeline.slam.gaussian_map import PARAMETER_NAMES, as_leaves, prune_mask
from pipeline.slam.kernels import EAGER, SlamKernels
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.optimizers import MapOptimizer, make_map_optimizer


def _learning_rates(config: MappingConfig) -> dict[str, float]:
    return {
        "means": config.lr_means,
        "quats": config.lr_rotations,
        "log_scales": config.lr_scales,
        "opacity_logits": config.lr_opacities,
        "colors": config.lr_colors,
    }


def _prune(optimizer: MapOptimizer, keep: torch.Tensor) -> Gaussians:
    """Drop Gaussians (all but the positions `keep` [M]) from the parameters and Adam's moments alike."""
    kept = {}
    for group in optimizer.param_groups:
        old = group["params"][0]
        new = old.detach()[keep].requires_grad_(True)
        state = optimizer.state.pop(old, None)
        if state:
            optimizer.state[new] = {k: v[keep] if k in ("exp_avg", "exp_avg_sq") else v for k, v in state.items()}
        group["params"] = [new]
        kept[group["name"]] = new
    return Gaussians(**kept)


@dataclass(frozen=True)
class MapSettings:
    """What mapping needs besides the map, the views and the run's random state."""

    renderer: Renderer
    render_views: ViewsRenderer
    config: MappingConfig
    loss: LossConfig
    near: float  # metres
    far: float
    kernels: SlamKernels = EAGER


def map_window(
    gaussians: Gaussians,
    views: list[Keyframe],
    intrinsics: torch.Tensor,
    scene_radius: float,
    rng: random.Random,
    settings: MapSettings,
) -> Gaussians:
    """`config.iters` view renders, drawn at random from `views`, `config.views_per_step` of them
    rendered together for each optimiser step (1: SplaTAM's one view per Adam step); pruning
    before the steps whose renders include an index of `config.prune_at` (Gaussians larger than
    `prune_scale_factor` x `scene_radius` metres go too).

    -> the optimised Gaussians (detached).
    """
    config = settings.config
    params = as_leaves(gaussians)
    rates = _learning_rates(config)
    groups = [{"params": [getattr(params, n)], "lr": rates[n], "name": n} for n in PARAMETER_NAMES]
    optimizer = make_map_optimizer(groups, config.optimizer, params.means.is_cuda)
    height, width = views[0].depth.shape
    cameras = [Camera(invert_pose(v.c2w), intrinsics, width, height, settings.near, settings.far) for v in views]
    per_step = config.views_per_step
    for first in range(0, config.iters, per_step):
        renders = range(first, min(first + per_step, config.iters))
        if any(i in config.prune_at for i in renders):
            with torch.no_grad():
                keep = prune_mask(params, config.prune_opacity, config.prune_scale_factor * scene_radius)
                keep = keep.nonzero()[:, 0]  # positions: the count is read back once, not per gathered tensor
            params = _prune(optimizer, keep)
        picks = [rng.randrange(len(views)) for _ in renders]
        loss, visible = _views_loss(params, [views[p] for p in picks], [cameras[p] for p in picks], settings)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step(visible)
    return Gaussians(*(getattr(params, n).detach() for n in PARAMETER_NAMES))


def _views_loss(
    params: Gaussians, views: list[Keyframe], cameras: list[Camera], settings: MapSettings
) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean mapping loss over the views, and the Gaussians any of them saw ([N] bool)."""
    config, weights, kernels = settings.config, settings.loss, settings.kernels
    outs = [settings.renderer(params, cameras[0])] if len(cameras) == 1 else settings.render_views(params, cameras)
    losses = [
        kernels.mapping_loss(
            out.color, out.depth, view.color, view.depth, config.ssim_weight, weights.depth_weight, weights.color_weight
        )
        for out, view in zip(outs, views)
    ]
    visible = outs[0].visible
    for out in outs[1:]:
        visible = visible | out.visible
    return (losses[0] if len(losses) == 1 else torch.stack(losses).mean()), visible
