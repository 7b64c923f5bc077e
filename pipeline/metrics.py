"""Trajectory and rendering metrics, named for exactly what they compute."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians, Renderer, RenderOutput
from pipeline.slam.losses import psnr, ssim_map


@dataclass
class TrajectoryError:
    rmse_m: float  # root of the mean squared camera-centre error after alignment
    mean_m: float  # mean camera-centre error after alignment
    median_m: float
    max_m: float
    frames: int


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation [3, 3] and translation [3] (no scale) taking points source [N, 3] onto target."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    u, _, vt = np.linalg.svd(cov)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ d @ vt
    return rotation, mu_t - rotation @ mu_s


def aligned_centre_errors(estimated_c2w: np.ndarray, reference_c2w: np.ndarray) -> np.ndarray:
    """Each camera centre's error [N, 3] metres (estimate minus reference) after the rigid
    (rotation + translation) alignment of the estimated poses [N, 4, 4] onto the reference."""
    est, ref = estimated_c2w[:, :3, 3], reference_c2w[:, :3, 3]
    rotation, translation = rigid_alignment(est, ref)
    aligned: np.ndarray = est @ rotation.T + translation - ref
    return aligned


def absolute_trajectory_error(estimated_c2w: np.ndarray, reference_c2w: np.ndarray) -> TrajectoryError:
    """ATE of camera centres [N, 4, 4] after a rigid (rotation + translation) alignment of the estimate."""
    errors = np.linalg.norm(aligned_centre_errors(estimated_c2w, reference_c2w), axis=1)
    return TrajectoryError(
        rmse_m=float(np.sqrt(np.mean(errors**2))),
        mean_m=float(errors.mean()),
        median_m=float(np.median(errors)),
        max_m=float(errors.max()),
        frames=len(errors),
    )


LARGE_STEP_M = 0.03  # metres: a reference motion between consecutive frames beyond this is a large step


@dataclass
class StepError:
    """The error of the estimated frame-to-frame motions over the reference's large steps: per
    step, the translation of inv(reference step) @ estimated step (the relative pose error over
    one frame)."""

    steps: int  # consecutive frames whose reference motion is over `min_step_m`
    mean_m: float  # 0 where there are none
    median_m: float
    max_m: float
    min_step_m: float


def each_step_error(estimated_c2w: np.ndarray, reference_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of camera-to-world poses [N, 4, 4] against their references [N, 4, 4] -> (each reference
    step's length [N-1] metres, the translation of inv(reference step) @ estimated step [N-1]
    metres). No alignment: a relative motion does not depend on the world frame."""
    estimated_steps = np.linalg.inv(estimated_c2w[:-1]) @ estimated_c2w[1:]
    reference_steps = np.linalg.inv(reference_c2w[:-1]) @ reference_c2w[1:]
    errors = np.linalg.norm((np.linalg.inv(reference_steps) @ estimated_steps)[:, :3, 3], axis=1)
    return np.linalg.norm(reference_steps[:, :3, 3], axis=1), errors


def step_errors(estimated_c2w: np.ndarray, reference_c2w: np.ndarray, min_step_m: float = LARGE_STEP_M) -> StepError:
    """Of camera-to-world poses [N, 4, 4] against their references [N, 4, 4] (`each_step_error`)."""
    lengths, each = each_step_error(estimated_c2w, reference_c2w)
    errors = each[lengths > min_step_m]
    if not len(errors):
        return StepError(0, 0.0, 0.0, 0.0, min_step_m)
    return StepError(len(errors), float(errors.mean()), float(np.median(errors)), float(errors.max()), min_step_m)


@dataclass
class ViewQuality:
    psnr_db: float
    ssim: float
    depth_l1_cm: float
    depth_rmse_cm: float  # root of the mean squared depth error: large errors weigh more than in L1
    render: RenderOutput | None = None  # the render compared, where asked for (keep_render)


@torch.no_grad()
def view_quality(
    renderer: Renderer,
    gaussians: Gaussians,
    frame: DeviceFrame,
    c2w: torch.Tensor,
    near: float,
    far: float,
    keep_render: bool = False,
) -> ViewQuality:
    """Render at the estimated pose and compare with the input over valid-depth pixels (the
    render itself kept with `keep_render`)."""
    camera = Camera(invert_pose(c2w), frame.intrinsics, frame.width, frame.height, near, far)
    out = renderer(gaussians, camera)
    kept = out if keep_render else None
    valid = frame.depth > 0
    if not bool(valid.any()):
        return ViewQuality(math.nan, math.nan, math.nan, math.nan, kept)
    color = out.color.clamp(0, 1)
    error = (out.depth - frame.depth)[valid]
    return ViewQuality(
        psnr_db=psnr(color, frame.color, valid),
        ssim=float(ssim_map(color, frame.color)[valid].mean()),
        depth_l1_cm=float(error.abs().mean()) * 100.0,
        depth_rmse_cm=float(error.square().mean().sqrt()) * 100.0,
        render=kept,
    )
