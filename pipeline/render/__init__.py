"""Differentiable rendering of Gaussians: colour, expected depth and silhouette in one call.

`make_renderer` picks the backend once; every caller then uses the same signature:
`renderer(gaussians, camera) -> RenderOutput`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import torch

from pipeline.config import GaussianConfig, RenderBackend, RenderConfig
from pipeline.errors import UserError
from pipeline.render.intersections import TileIntersections
from pipeline.render.reference import render_reference, render_reference_views
from pipeline.render.types import Camera, Gaussians, RenderOutput

Renderer = Callable[[Gaussians, Camera], RenderOutput]
ViewsRenderer = Callable[[Gaussians, list[Camera]], list[RenderOutput]]  # several cameras of one size at once
# Several cameras with their tile intersections at a fixed capacity (an int): no host read, so a
# CUDA graph can record it; the intersections say whether the capacity held them all.
CapacityRenderer = Callable[[Gaussians, list[Camera], int], tuple[list[RenderOutput], TileIntersections]]

FLAT_LOG_SCALE = -9.0  # log-scale of the normal axis when 2D Gaussians run on the reference backend

__all__ = [
    "Camera", "CapacityRenderer", "Gaussians", "RenderOutput", "Renderer", "TileIntersections", "ViewsRenderer",
    "make_capacity_renderer", "make_renderer", "make_views_renderer", "resolve_backend",
]  # fmt: skip


def resolve_backend(config: RenderConfig, device: torch.device) -> RenderBackend:
    if config.backend == "auto":
        return "gsplat" if device.type == "cuda" else "reference"
    if config.backend == "gsplat" and device.type != "cuda":
        raise UserError("render.backend=gsplat needs a CUDA device (use auto or reference)")
    return config.backend


def _flattened(render: Renderer) -> Renderer:
    """2D Gaussians on the reference backend: 3D Gaussians squashed along their third axis."""

    def render_flat(gaussians: Gaussians, camera: Camera) -> RenderOutput:
        scales = gaussians.log_scales.expand(-1, 3)
        flat = torch.cat([scales[:, :2], torch.full_like(scales[:, :1], FLAT_LOG_SCALE)], dim=1)
        squashed = Gaussians(gaussians.means, gaussians.quats, flat, gaussians.opacity_logits, gaussians.colors)
        return render(squashed, camera)

    return render_flat


def make_renderer(config: RenderConfig, gaussians: GaussianConfig, device: torch.device) -> Renderer:
    backend = resolve_backend(config, device)
    if backend == "gsplat":
        from pipeline.render import gsplat_backend

        fn = gsplat_backend.render_gsplat_2d if gaussians.kind == "2d" else gsplat_backend.render_gsplat_3d
        return partial(fn, eps2d=config.eps2d, packed=config.packed)
    reference = partial(render_reference, eps2d=config.eps2d)
    return _flattened(reference) if gaussians.kind == "2d" else reference


def make_views_renderer(config: RenderConfig, gaussians: GaussianConfig, device: torch.device) -> ViewsRenderer:
    """Several cameras in one call: one batched rasterisation with gsplat's unpacked 3D Gaussians
    (one launch of each kernel for all views), one camera after the other otherwise."""
    if resolve_backend(config, device) == "gsplat" and gaussians.kind == "3d" and not config.packed:
        from pipeline.render import gsplat_backend

        return partial(gsplat_backend.render_gsplat_3d_views, eps2d=config.eps2d)
    single = make_renderer(config, gaussians, device)
    return lambda splats, cameras: [single(splats, camera) for camera in cameras]


def make_capacity_renderer(
    config: RenderConfig, gaussians: GaussianConfig, device: torch.device
) -> CapacityRenderer | None:
    """The fixed-capacity render of 3D Gaussians (gsplat's kernels on CUDA, the reference on the
    CPU, both unpacked); None where there is none (2D Gaussians, `render.packed`)."""
    if gaussians.kind != "3d" or config.packed:
        return None
    if resolve_backend(config, device) == "gsplat":
        from pipeline.render import gsplat_backend

        return partial(gsplat_backend.render_gsplat_3d_capacity, eps2d=config.eps2d)
    return partial(render_reference_views, eps2d=config.eps2d)
