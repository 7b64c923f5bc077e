"""Camera tracking: optimise one pose against a frozen map by differentiable rendering."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Protocol

import torch

from pipeline.config import LossConfig, TrackingConfig, switched_on
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose, pose_matrix, rotmat_to_quat
from pipeline.render import Camera, CapacityRenderer, Gaussians, Renderer
from pipeline.slam.kernels import EAGER, SlamKernels
from pipeline.slam.tracking.align_tracker import AlignTracker, SolveReport


@dataclass(frozen=True)
class TrackSettings:
    """What tracking needs besides the map, the frame and the starting pose."""

    renderer: Renderer
    config: TrackingConfig
    loss: LossConfig
    near: float  # metres
    far: float
    kernels: SlamKernels = EAGER
    cuda: bool = False  # the frames are on a CUDA device (the align solve can then be graph-recorded)
    capacity_renderer: CapacityRenderer | None = None  # align: the fixed-capacity render, where there is one


@dataclass
class TrackResult:
    c2w: torch.Tensor  # [4, 4] the pose with the lowest loss seen
    best_loss: (
        torch.Tensor
    )  # [] that loss summed over the tracked pixels (device tensor; read it at the frame boundary)
    coverage: torch.Tensor  # [] fraction of valid-depth pixels tracked at that pose
    failure: str = ""  # why the method itself judges the pose unsound, if it does (align)
    solve: SolveReport | None = None  # align: its final solve's statistics (adam: None)


class Tracker(Protocol):
    """One frame's pose against a frozen map, from camera-to-world `c2w_init` [4, 4];
    `large_step`: the caller expects the frame far from its guess (align solves wide from the
    start; adam has no basin to widen)."""

    def __call__(
        self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, large_step: bool = False
    ) -> TrackResult: ...


def make_tracker(settings: TrackSettings) -> Tracker:
    """The configured tracking method: `adam` (SplaTAM's rendering loss optimised by Adam) or
    `align` (dense RGB-D alignment to one render, then `refine_iters` of adam's iterations)."""
    config = settings.config
    if config.method == "adam":
        return partial(track, settings=settings)
    capture = switched_on(config.align_graph, settings.cuda)
    fixed = settings.capacity_renderer if switched_on(config.align_fixed_capacity, settings.cuda) else None
    aligner = AlignTracker(
        settings.renderer, config, settings.near, settings.far, settings.kernels.align, capture, fixed
    )
    refine = replace(settings, config=replace(config, iters=config.refine_iters))
    return partial(track_aligned, aligner=aligner, refine=refine)


def track_aligned(
    gaussians: Gaussians,
    frame: DeviceFrame,
    c2w_init: torch.Tensor,
    large_step: bool = False,
    *,
    aligner: AlignTracker,
    refine: TrackSettings,
) -> TrackResult:
    """Align to the map rendered at camera-to-world `c2w_init` [4, 4] (`AlignTracker`; wide from
    the start with `large_step`), then `refine.config.iters` of adam's iterations from there
    (none: the loss is the alignment's squared point-to-plane residual, metres^2, over its
    inliers)."""
    aligned = aligner(gaussians, frame, c2w_init, wide=large_step)
    if refine.config.iters == 0:
        return TrackResult(aligned.c2w, aligned.geometric_sq, aligned.coverage, aligned.failure, aligned.report)
    return replace(track(gaussians, frame, aligned.c2w, settings=refine), failure=aligned.failure, solve=aligned.report)


def track(
    gaussians: Gaussians,
    frame: DeviceFrame,
    c2w_init: torch.Tensor,
    large_step: bool = False,
    *,
    settings: TrackSettings,
) -> TrackResult:
    """Fresh Adam on the world-to-camera quaternion and translation for `config.iters` steps,
    from camera-to-world `c2w_init` [4, 4] (`large_step` changes nothing: Adam's reach is its
    iterations).

    The Gaussians are frozen (passed without gradients). The best pose is chosen on the
    device: the loss at step i belongs to the parameters before step i's update.
    """
    config, weights, kernels = settings.config, settings.loss, settings.kernels
    w2c_init = invert_pose(c2w_init)
    quat = rotmat_to_quat(w2c_init[:3, :3]).clone().requires_grad_(True)
    trans = w2c_init[:3, 3].clone().requires_grad_(True)
    optimizer = torch.optim.Adam(
        [{"params": [quat], "lr": config.lr_rotation}, {"params": [trans], "lr": config.lr_translation}],
        eps=1e-15,
        fused=quat.is_cuda,
    )
    best_loss = torch.full((), float("inf"), device=quat.device)  # a fill: no host-to-device copy
    best_quat, best_trans = quat.detach().clone(), trans.detach().clone()
    best_coverage = torch.zeros((), device=quat.device)
    valid_pixels = (frame.depth > 0).sum().clamp(min=1)
    for _ in range(config.iters):
        w2c = pose_matrix(quat, trans)
        out = settings.renderer(
            gaussians, Camera(w2c, frame.intrinsics, frame.width, frame.height, settings.near, settings.far)
        )
        loss, tracked_pixels = kernels.tracking_loss(
            out.color, out.depth, out.silhouette, frame.color, frame.depth,
            config.silhouette_threshold, weights.depth_weight, weights.color_weight,
        )  # fmt: skip
        with torch.no_grad():
            better = loss < best_loss
            best_loss = torch.where(better, loss, best_loss)
            best_quat = torch.where(better, quat, best_quat)
            best_trans = torch.where(better, trans, best_trans)
            best_coverage = torch.where(better, tracked_pixels / valid_pixels, best_coverage)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    w2c = pose_matrix(best_quat, best_trans)
    return TrackResult(invert_pose(w2c), best_loss, best_coverage)
