"""Mapping: optimise the Gaussians against a window of keyframes with their poses fixed."""

from __future__ import annotations

import random
from dataclasses import dataclass

import torch

from pipeline.config import LossConfig, MappingConfig
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians, Renderer
from pipeline.slam.gaussian_map import PARAMETER_NAMES, as_leaves, prune_mask
from pipeline.slam.kernels import EAGER, SlamKernels
from pipeline.slam.keyframes import Keyframe


def _learning_rates(config: MappingConfig) -> dict[str, float]:
    return {
        "means": config.lr_means,
        "quats": config.lr_rotations,
        "log_scales": config.lr_scales,
        "opacity_logits": config.lr_opacities,
        "colors": config.lr_colors,
    }


def _prune(optimizer: torch.optim.Adam, keep: torch.Tensor) -> Gaussians:
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
    """`config.iters` Adam steps, each on one view drawn at random; pruning at `config.prune_at`
    (Gaussians larger than `prune_scale_factor` x `scene_radius` metres go too).

    -> the optimised Gaussians (detached).
    """
    config, weights, kernels = settings.config, settings.loss, settings.kernels
    params = as_leaves(gaussians)
    rates = _learning_rates(config)
    optimizer = torch.optim.Adam(
        [{"params": [getattr(params, n)], "lr": rates[n], "name": n} for n in PARAMETER_NAMES],
        eps=1e-15,
        fused=params.means.is_cuda,
    )
    height, width = views[0].depth.shape
    cameras = [Camera(invert_pose(v.c2w), intrinsics, width, height, settings.near, settings.far) for v in views]
    for step in range(config.iters):
        if step in config.prune_at:
            with torch.no_grad():
                keep = prune_mask(params, config.prune_opacity, config.prune_scale_factor * scene_radius)
                keep = keep.nonzero()[:, 0]  # positions: the count is read back once, not per gathered tensor
            params = _prune(optimizer, keep)
        pick = rng.randrange(len(views))
        out = settings.renderer(params, cameras[pick])
        view = views[pick]
        loss = kernels.mapping_loss(
            out.color, out.depth, view.color, view.depth, config.ssim_weight, weights.depth_weight, weights.color_weight
        )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return Gaussians(*(getattr(params, n).detach() for n in PARAMETER_NAMES))
