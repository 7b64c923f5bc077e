"""The small tensor functions run in every tracking and mapping iteration, compiled or not.

Each is a handful of element-wise kernels over the image; on the GPU the host time to launch
them rivals their run time, and `torch.compile` fuses them into a few kernels. The choice is
made once, here (`make_kernels`), not in the loops. The pose matrix is not compiled: in its
matrix-product form (`geometry.quat_to_rotmat`) it is a few kernels, and a compiled call's own
host overhead (~0.4 ms forward on the H200, `bench/results/iteration_costs*.json`) costs more.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from pipeline.compile_cache import persist_compile_cache
from pipeline.slam.losses import ssim
from pipeline.slam.tracking.rgbd_alignment import EAGER_ALIGN, AlignKernels, batched, lm_iteration


def tracking_loss(
    render_color: torch.Tensor,  # [H, W, 3]
    render_depth: torch.Tensor,  # [H, W] metres
    silhouette: torch.Tensor,  # [H, W]
    color: torch.Tensor,  # [H, W, 3] observed
    depth: torch.Tensor,  # [H, W] observed metres, 0 = invalid
    threshold: float,
    depth_weight: float,
    color_weight: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sum of L1 depth and colour errors over valid-depth pixels the map covers (silhouette >
    threshold) -> (loss [], number of those pixels [])."""
    mask = (depth > 0) & (silhouette > threshold)
    depth_l1 = torch.where(mask, (render_depth - depth).abs(), 0.0).sum()
    color_l1 = torch.where(mask[..., None], (render_color - color).abs(), 0.0).sum()
    return depth_weight * depth_l1 + color_weight * color_l1, mask.sum()


def mapping_loss(
    render_color: torch.Tensor,  # [H, W, 3]
    render_depth: torch.Tensor,  # [H, W] metres
    color: torch.Tensor,  # [H, W, 3] observed
    depth: torch.Tensor,  # [H, W] observed metres, 0 = invalid
    ssim_weight: float,
    depth_weight: float,
    color_weight: float,
) -> torch.Tensor:
    """Mean L1 depth over valid depth + colour (1 - w) x L1 + w x (1 - SSIM) over the image."""
    valid = depth > 0
    depth_l1 = torch.where(valid, (render_depth - depth).abs(), 0.0).sum() / valid.sum().clamp(min=1)
    color_l1 = (render_color - color).abs().mean()
    color_term = (1 - ssim_weight) * color_l1 + ssim_weight * (1 - ssim(render_color, color))
    return depth_weight * depth_l1 + color_weight * color_term


@dataclass(frozen=True)
class SlamKernels:
    tracking_loss: Callable[..., tuple[torch.Tensor, torch.Tensor]]
    mapping_loss: Callable[..., torch.Tensor]
    align: AlignKernels  # the align tracker's Levenberg-Marquardt iteration (per level), one start and a batch


def make_kernels(compiled: bool, compile_grid: bool = True) -> SlamKernels:
    """The kernels, compiled or not; compiled ones are cached in the user's cache folder
    (`compile_cache`), so that the next run on this machine does not compile them again. The
    align iteration compiles once per pyramid level's size: compiled for any size (one graph) it
    ran the H200's tracking 2.3-2.6x slower per frame (bench/NOTES.md, Change 21's outcome).
    `compile_grid` False leaves the grid's batched iteration uncompiled: tracing it under vmap is
    most of a warm start's compile time (bench/NOTES.md, Change 35)."""
    if not compiled:
        return SlamKernels(tracking_loss, mapping_loss, EAGER_ALIGN)
    cuda = torch.cuda.is_available()
    persist_compile_cache(torch.device("cuda", torch.cuda.current_device()) if cuda else torch.device("cpu"))
    batch = batched(lm_iteration)
    batch = torch.compile(batch, dynamic=False) if compile_grid else batch
    return SlamKernels(
        torch.compile(tracking_loss, dynamic=False),
        torch.compile(mapping_loss, dynamic=False),
        AlignKernels(torch.compile(lm_iteration, dynamic=False), batch),
    )


EAGER = make_kernels(compiled=False)
