"""The `align` tracking method: render the map once at the predicted pose (no backward pass),
align the new frame to that render densely (`rgbd_alignment`), judge the solve from its own
statistics, and try once more before the frame is declared lost."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch

from pipeline.config import TrackingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose, pose_matrix, rotmat_to_quat
from pipeline.render import Camera, Gaussians, Renderer, RenderOutput
from pipeline.slam.cuda_graphs import GraphCache
from pipeline.slam.tracking.pyramid import check_pyramid_fits, intensity, rgbd_pyramid
from pipeline.slam.tracking.rgbd_alignment import (
    AlignIteration,
    AlignParams,
    Linearisation,
    LmState,
    SourcePoints,
    TargetMaps,
    align,
    lm_iteration,
    source_points,
    target_maps,
)

MIN_PIXELS = 64  # fewer valid-depth pixels, or fewer inliers, and no pose is estimated


@dataclass(frozen=True)
class AlignResult:
    c2w: torch.Tensor  # [4, 4] camera-to-world
    geometric_sq: torch.Tensor  # [] sum of squared point-to-plane residuals over the inliers, metres^2
    coverage: torch.Tensor  # [] inliers / valid-depth pixels of the frame
    failure: str  # empty when the solve looks sound, else why not
    # The final normal equations [6, 6] float64 at `motion` [4, 4] float64 (this camera -> the
    # render's), for a left perturbation exp(xi) @ motion: a pose-graph edge's information
    # (`pose_graph.alignment_information`). Device tensors, not read back.
    hessian: torch.Tensor
    motion: torch.Tensor


@dataclass(frozen=True)
class SolveReport:
    """A solve's statistics on the host (one read per attempt)."""

    valid: int  # valid-depth pixels of the frame
    associated: int  # of them, projected onto valid render pixels
    inliers: int  # of those, within the depth gate
    rms_m: float  # RMS point-to-plane residual of the inliers
    rms_intensity: float  # RMS intensity residual of the inliers
    conditioning: float  # smallest / largest eigenvalue of the Jacobi-scaled normal equations

    def failure(self, config: TrackingConfig) -> str:
        """Empty when the solve looks sound, else the first reason it does not."""
        if self.valid < MIN_PIXELS:
            return f"no valid depth to align ({self.valid} pixels)"
        if self.inliers < MIN_PIXELS:
            return f"only {self.inliers} pixels fit the map"
        fraction = self.inliers / max(self.associated, 1)
        if fraction < config.align_min_inliers:
            return f"only {fraction:.0%} of the pixels on the map fit it (at least {config.align_min_inliers:.0%})"
        if self.conditioning < config.align_min_conditioning:
            return f"the alignment is ill-conditioned (eigenvalue ratio {self.conditioning:.1e})"
        if self.rms_m > config.align_max_residual_m:
            return f"point-to-plane residual {100 * self.rms_m:.1f} cm RMS"
        if self.rms_intensity > config.align_max_intensity_rms:
            return f"intensity residual {self.rms_intensity:.2f} RMS: the frame's colours do not match the map's"
        return ""


def conditioning(hessian: torch.Tensor) -> float:
    """Smallest / largest eigenvalue of D^-1/2 H D^-1/2 (D = diag H) for a [6, 6] host tensor:
    units cancel, so rotation and translation compare; 0 when a direction has no data at all."""
    diagonal = torch.diagonal(hessian)
    if not bool((diagonal > 0).all()):
        return 0.0
    scale = diagonal.rsqrt()
    eigenvalues = torch.linalg.eigvalsh(hessian * scale[:, None] * scale[None, :])
    return float(eigenvalues[0] / eigenvalues[-1])


def read_report(fit: Linearisation, valid: torch.Tensor) -> SolveReport:
    """One device-to-host copy of the solve's statistics; `valid` [M] the frame's valid depth."""
    counts = torch.stack([valid.sum(), fit.associated, fit.inliers]).double()
    squares = torch.stack([fit.geometric_sq, fit.photometric_sq]).double()
    packed = torch.cat([counts, squares, fit.hessian.reshape(-1)]).cpu()
    valid_n, associated, inliers = (int(x) for x in packed[:3])
    rms_m, rms_intensity = (float(x) for x in (packed[3:5] / max(inliers, 1)).sqrt())
    hessian = packed[5:].reshape(6, 6)
    return SolveReport(valid_n, associated, inliers, rms_m, rms_intensity, conditioning(hessian))


def level_params(config: TrackingConfig, levels: int) -> list[AlignParams]:
    """The residuals' scales and gate per pyramid level, finest first: the gate widens with a
    coarser pixel's footprint."""
    return [
        AlignParams(
            config.align_depth_sigma_m,
            config.align_color_sigma,
            config.align_photometric_weight,
            config.align_max_depth_diff_m * 2**level,
        )
        for level in range(levels)
    ]


def prepare_rgbd(
    color: torch.Tensor,
    depth: torch.Tensor,
    intrinsics: torch.Tensor,
    target_color: torch.Tensor,
    target_depth: torch.Tensor,
    silhouette: torch.Tensor,
    levels: int,
    min_silhouette: float,
) -> tuple[list[SourcePoints], list[TargetMaps]]:
    """A frame (colour [H, W, 3] in [0, 1], depth [H, W] metres, intrinsics [3, 3]) as source
    points and a target view (a render, or a stored keyframe with silhouette 1 where its depth
    is valid) as maps, `levels` pyramid levels each, finest first. The target counts where its
    silhouette passes `min_silhouette`; its intensity is normalised by the silhouette, as the
    renderer normalises depth."""
    sources = [source_points(level) for level in rgbd_pyramid(intensity(color), depth, intrinsics, levels)]
    masked_depth = torch.where(silhouette > min_silhouette, target_depth, torch.zeros_like(target_depth))
    gray = intensity(target_color) / silhouette.clamp(min=min_silhouette)
    targets = [target_maps(level) for level in rgbd_pyramid(gray, masked_depth, intrinsics, levels)]
    return sources, targets


class AlignTracker:
    """One frame's pose by dense alignment to a render of the frozen map at `c2w_init`."""

    def __init__(
        self,
        renderer: Renderer,
        config: TrackingConfig,
        near: float,
        far: float,
        iteration: AlignIteration = lm_iteration,
        capture: bool = False,
    ) -> None:
        """`capture`: on CUDA, record each solve as a CUDA graph and replay it (cuda_graphs.py)."""
        self.renderer, self.config, self.near, self.far, self.iteration = renderer, config, near, far, iteration
        self.params = level_params(config, len(config.align_iters))
        self.recovery_schedule = (config.align_recovery_iters, *config.align_iters[1:])
        solve = partial(self.solve_images, schedule=config.align_iters)
        recover = partial(self.solve_images, schedule=self.recovery_schedule)
        self._solve: Callable[..., tuple[LmState, torch.Tensor]] = GraphCache(solve) if capture else solve
        self._recover: Callable[..., tuple[LmState, torch.Tensor]] = GraphCache(recover) if capture else recover

    def __call__(self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor) -> AlignResult:
        check_pyramid_fits(len(self.params), frame.height, frame.width)
        rendered = self._render(gaussians, frame, c2w_init)
        images = (frame.color, frame.depth, frame.intrinsics, rendered.color, rendered.depth, rendered.silhouette)
        state, valid = self._solve(*images)
        report = read_report(state.fit, valid)
        failure = report.failure(self.config)
        if failure and report.valid >= MIN_PIXELS and self.config.align_recovery_iters > 0:
            # One recovery attempt: more coarse-level iterations widen the basin of convergence.
            retry, _ = self._recover(*images)
            retry_failure = read_report(retry.fit, valid).failure(self.config)
            if retry_failure:
                failure = f"{failure}; after a recovery attempt: {retry_failure}"
            else:
                state, failure = retry, ""
        return self._result(state, c2w_init, valid, failure)

    def solve_images(
        self,
        color: torch.Tensor,
        depth: torch.Tensor,
        intrinsics: torch.Tensor,
        render_color: torch.Tensor,
        render_depth: torch.Tensor,
        silhouette: torch.Tensor,
        schedule: tuple[int, ...],
    ) -> tuple[LmState, torch.Tensor]:
        """The frame (colour [H, W, 3], depth [H, W] metres, intrinsics [3, 3]) aligned to the
        render (colour, depth, silhouette at the frame's size) -> (the solve's last state, the
        frame's valid-depth mask [H x W] at full size). Tensors in and out only, so that it can
        be recorded as a CUDA graph."""
        sources, targets = self.prepare_images(color, depth, intrinsics, render_color, render_depth, silhouette)
        return self.solve(sources, targets, schedule), sources[0].valid

    def _render(self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor) -> RenderOutput:
        camera = Camera(invert_pose(c2w_init), frame.intrinsics, frame.width, frame.height, self.near, self.far)
        with torch.no_grad():
            return self.renderer(gaussians, camera)

    def prepare(self, frame: DeviceFrame, rendered: RenderOutput) -> tuple[list[SourcePoints], list[TargetMaps]]:
        """The frame's pyramid as points in its own camera and the render's as maps, finest first."""
        return self.prepare_images(
            frame.color, frame.depth, frame.intrinsics, rendered.color, rendered.depth, rendered.silhouette
        )

    def prepare_images(
        self,
        color: torch.Tensor,
        depth: torch.Tensor,
        intrinsics: torch.Tensor,
        render_color: torch.Tensor,
        render_depth: torch.Tensor,
        silhouette: torch.Tensor,
    ) -> tuple[list[SourcePoints], list[TargetMaps]]:
        """`prepare` on the images (`prepare_rgbd`)."""
        images = (color, depth, intrinsics, render_color, render_depth, silhouette)
        return prepare_rgbd(*images, len(self.params), self.config.align_min_silhouette)

    def solve(
        self, sources: list[SourcePoints], targets: list[TargetMaps], schedule: tuple[int, ...] | None = None
    ) -> LmState:
        """The coarse-to-fine solve (`align_iters`, or `schedule`) from the render's pose."""
        return align(sources, targets, self.params, schedule or self.config.align_iters, self.iteration)

    def _result(self, state: LmState, c2w_init: torch.Tensor, valid: torch.Tensor, failure: str) -> AlignResult:
        """The camera-to-world of the solve, re-orthonormalised (the prediction if it is not finite)."""
        c2w = c2w_init @ state.pose.to(c2w_init.dtype)  # the motion maps this camera into the render's
        c2w = pose_matrix(rotmat_to_quat(c2w[:3, :3]), c2w[:3, 3])  # exactly rigid: no drift in later products
        c2w = torch.where(torch.isfinite(c2w).all(), c2w, c2w_init)
        coverage = state.fit.inliers / valid.sum().clamp(min=1)
        return AlignResult(c2w, state.fit.geometric_sq, coverage, failure, state.fit.hessian, state.pose)
