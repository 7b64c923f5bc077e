"""Camera tracking: optimise one pose against a frozen map by differentiable rendering."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Protocol

import torch

from pipeline.config import LossConfig, TrackingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose, pose_matrix, rotmat_to_quat
from pipeline.render import Camera, Gaussians, Renderer
from pipeline.slam.kernels import EAGER, SlamKernels


@dataclass(frozen=True)
class TrackSettings:
    """What tracking needs besides the map, the frame and the starting pose."""

    renderer: Renderer
    config: TrackingConfig
    loss: LossConfig
    near: float  # metres
    far: float
    kernels: SlamKernels = EAGER


@dataclass
class TrackResult:
    c2w: torch.Tensor  # [4, 4] the pose with the lowest loss seen
    best_loss: torch.Tensor  # [] that loss (device tensor; read it at the frame boundary)
    coverage: torch.Tensor  # [] fraction of valid-depth pixels the map covered at that pose


class Tracker(Protocol):
    """One frame's pose against a frozen map, from camera-to-world `c2w_init` [4, 4]."""

    def __call__(self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor) -> TrackResult: ...


def make_tracker(settings: TrackSettings) -> Tracker:
    """The configured tracking method (SplaTAM's rendering loss optimised by Adam)."""
    return partial(track, settings=settings)


def track(gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, settings: TrackSettings) -> TrackResult:
    """Fresh Adam on the world-to-camera quaternion and translation for `config.iters` steps,
    from camera-to-world `c2w_init` [4, 4].

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
