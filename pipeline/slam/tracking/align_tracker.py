"""The `align` tracking method: render the map at the predicted pose (no backward pass), align
the new frame to that render densely (`rgbd_alignment`), judge the solve from its own
statistics, and try once more before the frame is declared lost; after a large step, render
again at the aligned pose and align once more (`AlignTracker`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import torch

from pipeline.config import TrackingConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import grid_around, invert_pose, motion_extent, pose_matrix, rotmat_to_quat
from pipeline.render import Camera, CapacityRenderer, Gaussians, Renderer, RenderOutput, TileIntersections
from pipeline.render.intersections import INTERSECTION_QUANTUM, grown_capacity
from pipeline.slam.cuda_graphs import GraphCache
from pipeline.slam.tracking.pyramid import check_pyramid_fits, intensity, rgbd_pyramid
from pipeline.slam.tracking.rgbd_alignment import (
    EAGER_ALIGN,
    AlignKernels,
    AlignParams,
    LmState,
    SourcePoints,
    TargetMaps,
    align,
    source_points,
    target_maps,
)

MIN_PIXELS = 64  # fewer valid-depth pixels, or fewer inliers, and no pose is estimated
WIDE_MIN_COARSE = 12  # pixels: the wide schedule's coarsest level keeps at least this shorter side


@dataclass(frozen=True)
class AlignResult:
    c2w: torch.Tensor  # [4, 4] camera-to-world
    geometric_sq: torch.Tensor  # [] sum of squared point-to-plane residuals over the inliers, metres^2
    coverage: torch.Tensor  # [] inliers / valid-depth pixels of the frame
    failure: str  # empty when the solve looks sound, else why not
    report: SolveReport  # the final solve's statistics, on the host
    # The final normal equations [6, 6] float64 at `motion` [4, 4] float64 (this camera -> the
    # render's), for a left perturbation exp(xi) @ motion: a pose-graph edge's information
    # (`pose_graph.alignment_information`). Device tensors, not read back.
    hessian: torch.Tensor
    motion: torch.Tensor


def is_large_step(moved_m: float, moved_deg: float, config: TrackingConfig) -> bool:
    """Whether a camera motion (metres, degrees) is large: over `align_large_step_m` or `_deg`."""
    return moved_m > config.align_large_step_m or moved_deg > config.align_large_step_deg


@dataclass(frozen=True)
class SolveReport:
    """A solve's statistics on the host (one read per attempt)."""

    valid: int  # valid-depth pixels of the frame
    associated: int  # of them, projected onto valid render pixels
    inliers: int  # of those, within the depth gate
    rms_m: float  # RMS point-to-plane residual of the inliers
    rms_intensity: float  # RMS intensity residual of the inliers
    conditioning: float  # smallest / largest eigenvalue of the Jacobi-scaled normal equations
    moved_m: float = 0.0  # how far the solve moved the camera from the pose rendered at, metres
    moved_deg: float = 0.0  # and turned it, degrees
    renders: int = 1  # renders of the map the frame took to reach this solve (`AlignTracker`)

    def large(self, config: TrackingConfig) -> bool:
        """Whether the solve moved the camera far from the render's pose (`is_large_step`)."""
        return is_large_step(self.moved_m, self.moved_deg, config)

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


def read_report(state: LmState, valid: torch.Tensor) -> SolveReport:
    """One device-to-host copy of a solve's statistics; `valid` [M] the frame's valid depth."""
    fit = state.fit
    counts = torch.stack([valid.sum(), fit.associated, fit.inliers]).double()
    squares = torch.stack([fit.geometric_sq, fit.photometric_sq]).double()
    packed = torch.cat([counts, squares, motion_extent(state.pose).double(), fit.hessian.reshape(-1)]).cpu()
    valid_n, associated, inliers = (int(x) for x in packed[:3])
    rms_m, rms_intensity = (float(x) for x in (packed[3:5] / max(inliers, 1)).sqrt())
    moved_m, moved_deg = (float(x) for x in packed[5:7])
    hessian = packed[7:].reshape(6, 6)
    return SolveReport(valid_n, associated, inliers, rms_m, rms_intensity, conditioning(hessian), moved_m, moved_deg)


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
    is valid) as maps, `levels` pyramid levels each, finest first (`source_pyramid`,
    `target_pyramid`)."""
    sources = source_pyramid(color, depth, intrinsics, levels)
    return sources, target_pyramid(target_color, target_depth, intrinsics, silhouette, levels, min_silhouette)


def source_pyramid(
    color: torch.Tensor, depth: torch.Tensor, intrinsics: torch.Tensor, levels: int
) -> list[SourcePoints]:
    """A frame (colour [H, W, 3] in [0, 1], depth [H, W] metres, intrinsics [3, 3]) as the points
    that alignment moves, `levels` pyramid levels, finest first."""
    return [source_points(level) for level in rgbd_pyramid(intensity(color), depth, intrinsics, levels)]


def target_pyramid(
    color: torch.Tensor,
    depth: torch.Tensor,
    intrinsics: torch.Tensor,
    silhouette: torch.Tensor,
    levels: int,
    min_silhouette: float,
) -> list[TargetMaps]:
    """A view aligned to (colour [H, W, 3], depth [H, W] metres, silhouette [H, W]) as maps,
    `levels` pyramid levels, finest first. It counts where its silhouette passes
    `min_silhouette`; its intensity is normalised by the silhouette, as the renderer normalises
    depth."""
    masked_depth = torch.where(silhouette > min_silhouette, depth, torch.zeros_like(depth))
    gray = intensity(color) / silhouette.clamp(min=min_silhouette)
    return [target_maps(level) for level in rgbd_pyramid(gray, masked_depth, intrinsics, levels)]


@dataclass(frozen=True)
class Pass:
    """One render and the solve against it."""

    state: LmState
    report: SolveReport
    valid: torch.Tensor  # [H x W] the frame's valid depth
    c2w_render: torch.Tensor  # [4, 4] the pose rendered at
    failure: str


class AlignTracker:
    """One frame's pose by dense alignment to renders of the frozen map.

    The first render is at the prediction `c2w_init`. A solve that moves the camera far from
    the pose it rendered at (`align_large_step_m` or `_deg`) was aligned to a view of the map
    from elsewhere: what the frame sees of a surface depends on where from (occlusions, the
    splats' blending, the part of the map in view), so the map is rendered again at the
    aligned pose and the frame aligned again from there, with the wide schedule
    (`align_wide_iters`: one pyramid level more and more coarse iterations, a wider basin),
    at most `align_max_renders` renders in all. A frame whose last solve still moved that far
    has stopped short of the map's pose for it: it fails (the tracking verdict flags it lost).
    A frame whose step the caller expects to be large (`wide`) is solved wide from the start,
    its coarse levels from a grid of starts around the prediction (`align_grid_m`,
    `best_grid_start`)."""

    def __init__(
        self,
        renderer: Renderer,
        config: TrackingConfig,
        near: float,
        far: float,
        kernels: AlignKernels = EAGER_ALIGN,
        capture: bool = False,
        capacity_renderer: CapacityRenderer | None = None,
        capacity: int = INTERSECTION_QUANTUM,
    ) -> None:
        """`kernels`: the Levenberg-Marquardt iteration, from one start and over the grid's starts.
        `capture`: on CUDA, record each solve as a CUDA graph and replay it (cuda_graphs.py).
        `capacity_renderer`: render at a fixed intersection capacity (starting at `capacity`),
        so that the render never waits for the host to read the intersection count back (as
        gsplat's own does); the count is read after the solve's statistics, and a pass whose
        intersections overflowed runs again with the capacity grown."""
        self.renderer, self.config, self.near, self.far, self.kernels = renderer, config, near, far, kernels
        self.capture = capture
        self.capacity_renderer, self.capacity = capacity_renderer, capacity
        self.params = level_params(config, len(config.align_iters))
        self._solvers: dict[tuple[tuple[int, ...], float], Callable[..., tuple[LmState, torch.Tensor]]] = {}
        self._warmed = not capture  # eager solves need no warm-up

    def __call__(
        self, gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, wide: bool = False
    ) -> AlignResult:
        check_pyramid_fits(len(self.params), frame.height, frame.width)
        config = self.config
        wide_schedule = fitting_schedule(config.align_wide_iters, frame.height, frame.width)
        first = (wide_schedule, config.align_grid_m) if wide else (config.align_iters, 0.0)
        attempt = self._pass(gaussians, frame, c2w_init, *first, wide_schedule)
        renders = 1
        while not attempt.failure and attempt.report.large(config):
            if renders == config.align_max_renders:
                if renders > 1:  # one render: as before this check, its solve is all there is
                    attempt = replace(attempt, failure=stopped_short(attempt.report, renders))
                break
            attempt = self._pass(gaussians, frame, self._c2w(attempt), wide_schedule, 0.0, wide_schedule)
            renders += 1
        return self._result(replace(attempt, report=replace(attempt.report, renders=renders)))

    def _pass(
        self,
        gaussians: Gaussians,
        frame: DeviceFrame,
        c2w_render: torch.Tensor,
        schedule: tuple[int, ...],
        grid_m: float,
        wide_schedule: tuple[int, ...],
    ) -> Pass:
        """Render at `c2w_render`, solve over `schedule` (from a grid of starts `grid_m` apart
        where that is not 0); a failed solve is tried once more over `wide_schedule` with
        `align_recovery_iters` at its coarsest level (a wider basin)."""
        rendered, hits = self._render(gaussians, frame, c2w_render)
        images = (frame.color, frame.depth, frame.intrinsics, rendered.color, rendered.depth, rendered.silhouette)
        recovery = (self.config.align_recovery_iters, *wide_schedule[1:])
        if not self._warmed:
            self._warm_up(images, ((wide_schedule, 0.0), (wide_schedule, self.config.align_grid_m), (recovery, 0.0)))
        state, valid = self._solver(schedule, grid_m, frame.color.device)(*images)
        report = read_report(state, valid)
        if hits is not None and self._overflowed(hits):  # read after the report's: the GPU is done by then
            return self._pass(gaussians, frame, c2w_render, schedule, grid_m, wide_schedule)
        failure = report.failure(self.config)
        if failure and report.valid >= MIN_PIXELS and self.config.align_recovery_iters > 0:
            retry, _ = self._solver(recovery, 0.0, frame.color.device)(*images)
            retry_report = read_report(retry, valid)
            retry_failure = retry_report.failure(self.config)
            if retry_failure:
                failure = f"{failure}; after a recovery attempt: {retry_failure}"
            else:
                state, report, failure = retry, retry_report, ""
        return Pass(state, report, valid, c2w_render, failure)

    def _warm_up(self, images: tuple[torch.Tensor, ...], solves: tuple[tuple[tuple[int, ...], float], ...]) -> None:
        """On the first frame, compile and record the solves that later frames may need (the
        wide schedule, from one start and from the grid, and the recovery schedule: a pyramid
        level more), so that a frame mid-run never waits seconds for a compile; their results
        are dropped."""
        self._warmed = True
        for schedule, grid_m in solves:
            self._solver(schedule, grid_m, images[0].device)(*images)

    def _solver(
        self, schedule: tuple[int, ...], grid_m: float, device: torch.device
    ) -> Callable[..., tuple[LmState, torch.Tensor]]:
        """`solve_images` over `schedule` from a grid `grid_m` apart, made (and with `capture`,
        graph-recorded) once per schedule and grid. The grid's poses are made here, outside any
        recording: a copy from pageable host memory cannot be captured."""
        key = (schedule, grid_m)
        if key not in self._solvers:
            starts = grid_around(torch.eye(4, dtype=torch.float64), grid_m).to(device) if grid_m else None
            solve = partial(self.solve_images, schedule=schedule, starts=starts)
            self._solvers[key] = GraphCache(solve) if self.capture else solve
        return self._solvers[key]

    def solve_images(
        self,
        color: torch.Tensor,
        depth: torch.Tensor,
        intrinsics: torch.Tensor,
        render_color: torch.Tensor,
        render_depth: torch.Tensor,
        silhouette: torch.Tensor,
        schedule: tuple[int, ...],
        starts: torch.Tensor | None = None,
    ) -> tuple[LmState, torch.Tensor]:
        """The frame (colour [H, W, 3], depth [H, W] metres, intrinsics [3, 3]) aligned to the
        render (colour, depth, silhouette at the frame's size) over `schedule` (one pyramid
        level per entry), its coarse levels from each of `starts` where given ([S, 4, 4] float64
        on the images' device: the frame's camera relative to the render's, `grid_around`) and
        its finest from the best of them (`best_grid_start`) -> (the solve's last state, the
        frame's valid-depth mask [H x W] at full size). Tensors in and out only, so that it can
        be recorded as a CUDA graph."""
        images = (color, depth, intrinsics, render_color, render_depth, silhouette)
        sources, targets = prepare_rgbd(*images, len(schedule), self.config.align_min_silhouette)
        if starts is None or len(schedule) < 2:
            return self.solve(sources, targets, schedule), sources[0].valid
        params = level_params(self.config, len(schedule))
        coarse = align(sources[1:], targets[1:], params[1:], schedule[:-1], self.kernels.batch, starts)
        start = best_grid_start(coarse, self.config.align_min_inliers)
        return align(sources[:1], targets[:1], params[:1], schedule[-1:], self.kernels.one, start), sources[0].valid

    def _render(
        self, gaussians: Gaussians, frame: DeviceFrame, c2w: torch.Tensor
    ) -> tuple[RenderOutput, TileIntersections | None]:
        """The map at camera-to-world `c2w` [4, 4], with its intersections where they are at a
        fixed capacity (None: gsplat's own render, which sized them from the count it read)."""
        camera = Camera(invert_pose(c2w), frame.intrinsics, frame.width, frame.height, self.near, self.far)
        with torch.no_grad():
            if self.capacity_renderer is None:
                return self.renderer(gaussians, camera), None
            outputs, hits = self.capacity_renderer(gaussians, [camera], self.capacity)
            return outputs[0], hits

    def _overflowed(self, hits: TileIntersections) -> bool:
        """Whether the render lost intersections; if so the capacity grows to hold them."""
        count = int(hits.count)
        if count <= hits.capacity:
            return False
        self.capacity = grown_capacity(count, INTERSECTION_QUANTUM)
        return True

    def prepare(self, frame: DeviceFrame, rendered: RenderOutput) -> tuple[list[SourcePoints], list[TargetMaps]]:
        """The frame's pyramid as points in its own camera and the render's as maps, finest first
        (`align_iters`' levels)."""
        images = (frame.color, frame.depth, frame.intrinsics, rendered.color, rendered.depth, rendered.silhouette)
        return prepare_rgbd(*images, len(self.params), self.config.align_min_silhouette)

    def solve(
        self, sources: list[SourcePoints], targets: list[TargetMaps], schedule: tuple[int, ...] | None = None
    ) -> LmState:
        """The coarse-to-fine solve (`align_iters`, or `schedule`: as many levels as the pyramids
        hold) from the render's pose."""
        schedule = schedule or self.config.align_iters
        params = level_params(self.config, len(schedule))
        return align(sources, targets, params, schedule, self.kernels.one)

    @staticmethod
    def _c2w(attempt: Pass) -> torch.Tensor:
        """The camera-to-world of a pass's solve, re-orthonormalised (the pose rendered at if it
        is not finite)."""
        c2w_render = attempt.c2w_render
        c2w = c2w_render @ attempt.state.pose.to(c2w_render.dtype)  # the motion maps this camera into the render's
        c2w = pose_matrix(rotmat_to_quat(c2w[:3, :3]), c2w[:3, 3])  # exactly rigid: no drift in later products
        return torch.where(torch.isfinite(c2w).all(), c2w, c2w_render)

    def _result(self, attempt: Pass) -> AlignResult:
        fit = attempt.state.fit
        coverage = fit.inliers / attempt.valid.sum().clamp(min=1)
        c2w = self._c2w(attempt)
        return AlignResult(
            c2w, fit.geometric_sq, coverage, attempt.failure, attempt.report, fit.hessian, attempt.state.pose
        )


def best_grid_start(solves: LmState, min_inliers: float) -> torch.Tensor:
    """[4, 4] float64: of the coarse solves from a grid of starts (a batch: each field with a
    leading dimension), the pose of the one of least RMS point-to-plane residual among those
    whose inliers are at least `min_inliers` of the pixels associated (the first where none is):
    on the device, nothing read back.

    Why a grid: on real fast motion (a loop round a cabinet, 17 cm and 7 degrees a frame) a
    solve from a prediction 5-13 cm and 4-15 degrees off turns the camera nearly right and
    takes the rest of the error as a sideways step, a minimum 10-20 cm from the truth; the
    least residual over starts 15 cm apart picks the right basin (bench/NOTES.md, Change 25)."""
    fit = solves.fit
    rms = (fit.geometric_sq.double() / fit.inliers.clamp(min=1)).sqrt()
    enough = (fit.inliers >= min_inliers * fit.associated) & (fit.inliers > 0)
    ranked = torch.where(enough, rms, torch.full_like(rms, float("inf")))
    # not pose[argmin]: indexing by a 0-d tensor reads it to the host (no CUDA-graph recording then)
    return solves.pose.index_select(0, ranked.argmin().reshape(1))[0]


def fitting_schedule(schedule: tuple[int, ...], height: int, width: int) -> tuple[int, ...]:
    """`schedule` (iterations per level, coarse to fine) for a `height` x `width` frame: levels
    whose shorter side would fall under WIDE_MIN_COARSE pixels go, the next level taking over
    the coarsest's iterations (a coarse level of a few dozen pixels aligns to anything)."""
    levels = len(schedule)
    while levels > 1 and min(height, width) >> (levels - 1) < WIDE_MIN_COARSE:
        levels -= 1
    return schedule if levels == len(schedule) else (schedule[0], *schedule[len(schedule) - levels + 1 :])


def stopped_short(report: SolveReport, renders: int) -> str:
    """Why a frame whose last solve still moved far fails."""
    return (
        f"the alignment stopped short: after {renders} renders its last solve still moved"
        f" {100 * report.moved_m:.1f} cm, {report.moved_deg:.1f} deg"
    )
