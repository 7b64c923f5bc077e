"""The small tensor functions run in every tracking and mapping iteration, compiled or not.

Each is a handful of element-wise kernels over the image; on the GPU the host time to launch
them rivals their run time, and `torch.compile` fuses them into a few kernels. The choice is
made once, here (`make_kernels`), not in the loops. The pose matrix is not compiled: in its
matrix-product form (`geometry.quat_to_rotmat`) it is a few kernels, and a compiled call's own
host overhead (~0.4 ms forward on the H200, `bench/results/iteration_costs*.json`) costs more.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import ParamSpec, TypeVar

import torch
import torch._functorch.config as functorch_config

from pipeline.compile_cache import compile_cache_folder, persist_compile_cache
from pipeline.slam.cuda_graphs import DEVICE_WIDE
from pipeline.slam.losses import ssim
from pipeline.slam.precompiled import Precompiled
from pipeline.slam.tracking.rgbd_alignment import EAGER_ALIGN, AlignIteration, AlignKernels, lm_iteration, lm_iterations


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


P = ParamSpec("P")
R = TypeVar("R")


def one_thread_at_a_time(compiled: Callable[P, R]) -> Callable[P, R]:
    """A compiled function called under the device-wide lock (`cuda_graphs.DEVICE_WIDE`). A
    compile traces with FX, which sets a process-wide flag under which every other thread's call
    of a compiled function fails ("using FX to symbolically trace a dynamo-optimized function":
    the mapping thread under `slam.schedule=thread`, measured on the H200 at 6a71ace). Dynamo's
    own lock serialises compiles, not calls. Uncontended (one side per process), the lock costs
    under a microsecond a call; replayed CUDA graphs do not call these at all."""

    @functools.wraps(compiled)
    def call(*args: P.args, **kwargs: P.kwargs) -> R:
        with DEVICE_WIDE:
            return compiled(*args, **kwargs)

    return call


def compile_whole(fn: Callable[P, R]) -> Callable[P, R]:
    """torch.compile for fixed shapes, its backward compiled with its forward (in the first call,
    under the lock) rather than lazily at the first backward, outside it, where its FX tracing
    would fail the other side's compiled calls."""
    if hasattr(functorch_config, "force_non_lazy_backward_lowering"):  # (not in every torch release)
        functorch_config.force_non_lazy_backward_lowering = True
    return one_thread_at_a_time(torch.compile(fn, dynamic=False))


@dataclass(frozen=True)
class SlamKernels:
    tracking_loss: Callable[..., tuple[torch.Tensor, torch.Tensor]]
    mapping_loss: Callable[..., torch.Tensor]
    align: AlignKernels  # the align tracker's Levenberg-Marquardt iteration (per level), one start and a batch


def make_kernels(compiled: bool, compile_grid: bool = True, precompile: bool = False) -> SlamKernels:
    """The kernels, compiled or not; compiled ones are cached in the user's cache folder
    (`compile_cache`), so that the next run on this machine does not compile them again. The
    align iteration compiles once per pyramid level's size: compiled for any size (one graph) it
    ran the H200's tracking 2.3-2.6x slower per frame (bench/NOTES.md, Change 21's outcome).
    `compile_grid` False leaves the grid's batched iteration uncompiled: tracing it under vmap is
    most of a warm start's compile time (bench/NOTES.md, Change 35). `precompile` makes the
    compiled align iterations and the mapping loss (its forward and backward) AOTInductor
    packages, loaded in later runs without tracing (`precompiled.py`, Changes 36-38); adam's
    tracking loss stays torch.compile'd (`align` tracks without it)."""
    if not compiled:
        return SlamKernels(tracking_loss, mapping_loss, EAGER_ALIGN)
    device = torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    persist_compile_cache(device)
    one: AlignIteration = compile_whole(lm_iteration)
    grid: AlignIteration = compile_whole(lm_iterations) if compile_grid else lm_iterations
    mapping: Callable[..., torch.Tensor] = compile_whole(mapping_loss)
    if precompile:
        folder = compile_cache_folder(device, "aoti")
        one = Precompiled(lm_iteration, "lm_iteration", folder, fallback=one)
        grid = Precompiled(lm_iterations, "lm_iterations", folder, fallback=grid) if compile_grid else grid
        mapping = Precompiled(mapping_loss, "mapping_loss", folder, fallback=mapping, joint=True)
    return SlamKernels(compile_whole(tracking_loss), mapping, AlignKernels(one, grid))


EAGER = make_kernels(compiled=False)
