"""Dense RGB-D alignment of a frame against a rendered view: residuals, analytic Jacobians and a
Levenberg-Marquardt solve on se(3), coarse to fine.

The new frame is the source, the render the target. Every valid-depth source pixel is lifted to
a point p_s (source camera, metres), moved by the unknown motion T (source camera -> target
camera) and projected into the target, where the target's maps are sampled bilinearly
(projective association). Two residuals per pixel:

- point-to-plane, metres: r_g = n . (T p_s - q), with q and n the target's vertex and normal;
- photometric: r_c = I_t(pi(T p_s)) - I_s(u) - o, intensities in [0, 1], o the mean of
  I_t - I_s over the inliers (a change of the camera's exposure is not a motion).

Both are divided by their scales (`AlignParams`) and weighted by Huber's function. A pixel takes
part (an inlier) when the target is valid around its projection and |r_g| is under the depth gate.
Jacobians are for a left perturbation T <- exp(xi) T with xi = (rotation, translation).

Shapes are static throughout (masks instead of selections, the step chosen with torch.where),
so one iteration (`lm_iteration`) can be compiled per pyramid level; nothing is read back.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch.utils._pytree import tree_map

from pipeline.geometry import backproject, pixel_grid, se3_exp
from pipeline.slam.tracking.pyramid import RgbdLevel, same_surface

MIN_DEPTH = 1e-3  # metres: points closer to the target camera are not associated
VALID_SAMPLE = 0.5  # the bilinearly sampled (eroded) validity: the nearest target pixel is valid
INITIAL_DAMPING = 1e-4  # Marquardt's lambda, relative to the normal equations' diagonal
DAMPING_DOWN, DAMPING_UP = 0.5, 4.0  # after an accepted / a rejected step
DAMPING_RANGE = (1e-7, 1e4)
DIAGONAL_FLOOR = 1e-3  # x the mean diagonal: bounds steps along directions the data do not fix

# The channels of the target's maps, sampled in one call.
VERTEX, NORMAL, INTENSITY, GRADIENT, VALID = slice(0, 3), slice(3, 6), 6, slice(7, 9), 9


class AlignParams(NamedTuple):
    """The residuals' scales and gate at one pyramid level."""

    depth_sigma: float  # metres: point-to-plane residual of Huber weight 1 at most
    color_sigma: float  # intensity: the same for the photometric residual
    photometric_weight: float  # the photometric term's weight against the geometric one
    max_depth_diff: float  # metres: the gate on |r_g|


class SourcePoints(NamedTuple):
    """One pyramid level of the new frame, flattened (M = h x w)."""

    points: torch.Tensor  # [M, 3] source camera, metres (meaningless where not valid)
    intensity: torch.Tensor  # [M]
    valid: torch.Tensor  # [M] bool: valid depth


class TargetMaps(NamedTuple):
    """One pyramid level of the render, as maps sampled at projected points."""

    # [10, h, w]: vertex xyz (target camera, metres), unit normal xyz, intensity, its gradient
    # d/du and d/dv (per pixel), validity (eroded); see the channel slices above
    maps: torch.Tensor
    intrinsics: torch.Tensor  # [3, 3] at this level


class Linearisation(NamedTuple):
    """The normal equations and statistics at one pose."""

    hessian: torch.Tensor  # [6, 6] float64, sum of w J^T J over inliers (normalised residuals)
    gradient: torch.Tensor  # [6] float64, sum of w J^T r
    cost: torch.Tensor  # [] float64, robust cost over valid source pixels (outliers at the gate's cost)
    inliers: torch.Tensor  # [] pixels that took part
    associated: torch.Tensor  # [] pixels that projected onto valid target pixels
    geometric_sq: torch.Tensor  # [] sum of r_g^2 over inliers, metres^2
    photometric_sq: torch.Tensor  # [] sum of r_c^2 over inliers


class LmState(NamedTuple):
    pose: torch.Tensor  # [4, 4] float64: the best motion (source camera -> target camera) evaluated
    candidate: torch.Tensor  # [4, 4] float64: the next motion to evaluate
    damping: torch.Tensor  # [] float64
    fit: Linearisation  # at `pose`


def camera_points(depth: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Depth [h, w] metres -> the pixels' points [h, w, 3] in their camera's frame."""
    u, v = pixel_grid(depth.shape[0], depth.shape[1], depth.device)
    eye = torch.eye(4, dtype=depth.dtype, device=depth.device)
    return backproject(u, v, depth, intrinsics, eye)


def source_points(level: RgbdLevel) -> SourcePoints:
    points = camera_points(level.depth, level.intrinsics)
    return SourcePoints(points.reshape(-1, 3), level.intensity.reshape(-1), level.depth.reshape(-1) > 0)


def _pad(interior: torch.Tensor) -> torch.Tensor:
    """[h - 2, w - 2, ...] -> [h, w, ...] with a border of zeros."""
    widths = [0, 0] * (interior.dim() - 2) + [1, 1, 1, 1]
    return F.pad(interior, widths)


def normal_map(
    vertices: torch.Tensor, depth: torch.Tensor, intrinsics: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices [h, w, 3] of depth [h, w] metres -> (unit normals [h, w, 3] facing the camera,
    validity [h, w] bool). From central differences; valid where the pixel and its four
    neighbours have depth and no neighbour is across a depth edge (`same_surface`)."""
    du = vertices[1:-1, 2:] - vertices[1:-1, :-2]
    dv = vertices[2:, 1:-1] - vertices[:-2, 1:-1]
    normals = F.normalize(torch.linalg.cross(du, dv), dim=-1)
    centre = vertices[1:-1, 1:-1]
    normals = torch.where((normals * centre).sum(-1, keepdim=True) > 0, -normals, normals)
    z = depth[1:-1, 1:-1]
    neighbours = torch.stack([depth[1:-1, 2:], depth[1:-1, :-2], depth[2:, 1:-1], depth[:-2, 1:-1]], dim=-1)
    focal = torch.minimum(intrinsics[0, 0], intrinsics[1, 1])
    close = same_surface(neighbours, z[..., None], focal).all(-1)
    valid = (z > 0) & (neighbours > 0).all(-1) & close
    return _pad(normals), _pad(valid)


def intensity_gradients(gray: torch.Tensor) -> torch.Tensor:
    """Intensity [h, w] -> central-difference gradients [h, w, 2] (d/du, d/dv per pixel), 0 on the border."""
    du = (gray[1:-1, 2:] - gray[1:-1, :-2]) / 2
    dv = (gray[2:, 1:-1] - gray[:-2, 1:-1]) / 2
    return _pad(torch.stack([du, dv], dim=-1))


def target_maps(level: RgbdLevel) -> TargetMaps:
    """The render's vertex, normal, intensity, gradient and validity maps at one level."""
    vertices = camera_points(level.depth, level.intrinsics)
    normals, valid = normal_map(vertices, level.depth, level.intrinsics)
    # Eroded by one pixel: a point whose nearest pixel passes has four valid bilinear neighbours,
    # and association changes where that nearest pixel does, not at every sub-pixel shift.
    eroded = -F.max_pool2d(-valid[None, None].float(), 3, stride=1, padding=1)[0, 0]
    stacked = torch.cat(
        [vertices, normals, level.intensity[..., None], intensity_gradients(level.intensity), eroded[..., None]],
        dim=-1,
    )
    return TargetMaps(stacked.permute(2, 0, 1).contiguous(), level.intrinsics)


def sample_bilinear(maps: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Maps [C, h, w] at continuous pixel coordinates uv [M, 2] (pixel (u, v) centred at
    (u + 0.5, v + 0.5)) -> [M, C]; zero outside the image."""
    height, width = maps.shape[-2:]
    grid = torch.stack([uv[:, 0] * (2.0 / width) - 1.0, uv[:, 1] * (2.0 / height) - 1.0], dim=-1)
    grid = grid[None, None]  # [1, 1, M, 2] in grid_sample's [-1, 1]
    sampled = F.grid_sample(maps[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return sampled[0, :, 0].T


def point_to_plane_jacobian(points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """d(n . (exp(xi) p - q)) / d xi at xi = 0 for points p [M, 3] (target camera) and normals
    [M, 3] held fixed -> [M, 6] = (p x n, n)."""
    return torch.cat([torch.linalg.cross(points, normals), normals], dim=-1)


def photometric_jacobian(points: torch.Tensor, gradients: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """d I(pi(exp(xi) p)) / d xi at xi = 0 for points p [M, 3] (target camera, z > 0) and the
    image gradient [M, 2] (per pixel) at their projections -> [M, 6] = (p x a, a), where
    a = (d pi / d p)^T grad I."""
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    x, y, z = points.unbind(-1)
    gu, gv = gradients.unbind(-1)
    a = torch.stack([gu * fx / z, gv * fy / z, -(gu * fx * x + gv * fy * y) / (z * z)], dim=-1)
    return torch.cat([torch.linalg.cross(points, a), a], dim=-1)


def project_points(points: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Points [M, 3] (camera frame, z > 0) -> continuous pixel coordinates [M, 2]."""
    z = points[:, 2]
    return torch.stack(
        [
            intrinsics[0, 0] * points[:, 0] / z + intrinsics[0, 2],
            intrinsics[1, 1] * points[:, 1] / z + intrinsics[1, 2],
        ],
        dim=-1,
    )


def huber_weight(error: torch.Tensor) -> torch.Tensor:
    """IRLS weight of Huber's function at threshold 1 for normalised residuals."""
    return torch.where(error.abs() <= 1, torch.ones_like(error), 1 / error.abs().clamp(min=1))


def huber_cost(error: torch.Tensor) -> torch.Tensor:
    magnitude = error.abs()
    return torch.where(magnitude <= 1, 0.5 * error * error, magnitude - 0.5)


def _huber_at(value: float) -> float:
    return 0.5 * value * value if value <= 1 else value - 0.5


class Association(NamedTuple):
    """The source points at one motion, paired with the target's maps by projection."""

    points: torch.Tensor  # [M, 3] target camera, metres (a dummy (1, 1, 1) where not in front)
    normals: torch.Tensor  # [M, 3] the target's unit normals there
    gradients: torch.Tensor  # [M, 2] the target's intensity gradients there
    r_geometric: torch.Tensor  # [M] point-to-plane residual, metres
    r_photometric: torch.Tensor  # [M] intensity residual, less its mean over the inliers
    associated: torch.Tensor  # [M] bool: projected onto the valid target
    inlier: torch.Tensor  # [M] bool: associated and within the depth gate


def associate(pose: torch.Tensor, source: SourcePoints, target: TargetMaps, max_depth_diff: float) -> Association:
    """Projective association at the motion `pose` [4, 4] (float64, source camera -> target camera)."""
    rotation, translation = pose[:3, :3].float(), pose[:3, 3].float()
    points = source.points @ rotation.T + translation
    in_front = source.valid & (points[:, 2] > MIN_DEPTH)
    points = torch.where(in_front[:, None], points, torch.ones_like(points))  # no division by ~0 below
    sampled = sample_bilinear(target.maps, project_points(points, target.intrinsics))
    normals = F.normalize(sampled[:, NORMAL], dim=-1)
    associated = in_front & (sampled[:, VALID] > VALID_SAMPLE)
    r_geometric = ((points - sampled[:, VERTEX]) * normals).sum(-1)
    inlier = associated & (r_geometric.abs() < max_depth_diff)
    difference = sampled[:, INTENSITY] - source.intensity
    offset = torch.where(inlier, difference, torch.zeros_like(difference)).sum() / inlier.sum().clamp(min=1)
    r_photometric = difference - offset
    return Association(points, normals, sampled[:, GRADIENT], r_geometric, r_photometric, associated, inlier)


def robust_cost(pair: Association, valid: torch.Tensor, params: AlignParams) -> torch.Tensor:
    """The cost that Levenberg-Marquardt compares between motions -> [] float64: per valid
    source pixel, Huber of both normalised residuals for an inlier, and for any other pixel the
    most an inlier can cost (so losing pixels never pays and the count of pixels is fixed)."""
    most = _huber_at(params.max_depth_diff / params.depth_sigma) + params.photometric_weight * _huber_at(
        1 / params.color_sigma
    )
    cost = huber_cost(pair.r_geometric / params.depth_sigma) + params.photometric_weight * huber_cost(
        pair.r_photometric / params.color_sigma
    )
    cost = torch.where(pair.inlier, cost.clamp(max=most), torch.full_like(cost, most))
    return torch.where(valid, cost, torch.zeros_like(cost)).double().sum()


def linearise(pose: torch.Tensor, source: SourcePoints, target: TargetMaps, params: AlignParams) -> Linearisation:
    """The weighted normal equations, cost and counts at the motion `pose` [4, 4] (float64,
    source camera -> target camera), residuals normalised by their scales."""
    pair = associate(pose, source, target, params.max_depth_diff)
    e_geometric, e_photometric = pair.r_geometric / params.depth_sigma, pair.r_photometric / params.color_sigma
    zero = torch.zeros_like(e_geometric)
    root_w_geometric = torch.where(pair.inlier, huber_weight(e_geometric), zero).sqrt()
    root_w_photometric = torch.where(pair.inlier, params.photometric_weight * huber_weight(e_photometric), zero).sqrt()
    j_geometric = point_to_plane_jacobian(pair.points, pair.normals) / params.depth_sigma
    j_photometric = photometric_jacobian(pair.points, pair.gradients, target.intrinsics) / params.color_sigma
    rows = torch.cat([j_geometric * root_w_geometric[:, None], j_photometric * root_w_photometric[:, None]]).double()
    residuals = torch.cat([e_geometric * root_w_geometric, e_photometric * root_w_photometric]).double()
    geometric_sq = torch.where(pair.inlier, pair.r_geometric * pair.r_geometric, zero).sum()
    photometric_sq = torch.where(pair.inlier, pair.r_photometric * pair.r_photometric, zero).sum()
    return Linearisation(
        rows.T @ rows,  # [6, 6]
        rows.T @ residuals,  # [6]
        robust_cost(pair, source.valid, params),
        pair.inlier.sum(),
        pair.associated.sum(),
        geometric_sq,
        photometric_sq,
    )


def damped_step(hessian: torch.Tensor, gradient: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
    """The Levenberg-Marquardt step [6] (float64): (H + damping diag(H) + floor I) xi = -g;
    zero if the system cannot be solved."""
    diagonal = torch.diagonal(hessian)
    floor = DIAGONAL_FLOOR * diagonal.mean() + 1e-12
    system = hessian + torch.diag(damping * diagonal + floor)
    step, definite = solve_positive_definite(system, -gradient)
    usable = definite & torch.isfinite(step).all()
    return torch.where(usable, step, torch.zeros_like(step))


def solve_positive_definite(system: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x [n] with `system` [n, n] (symmetric) x = `rhs` [n] by Gauss-Jordan elimination without
    row exchanges, written out as tensor operations (n of a few), and whether `system` is
    positive definite (a 0-d bool: every pivot positive, as they are exactly then).

    Not torch.linalg: under `lm_iterations` a batch of factorisations goes to MAGMA on CUDA, which
    allocates device memory and so cannot be recorded in a CUDA graph. Written out it is four
    element-wise kernels a column (which the compiled iteration fuses); a positive definite
    system needs no row exchanges."""
    n = system.shape[-1]
    augmented = torch.cat([system, rhs[:, None]], dim=1)  # [n, n + 1]
    rows = torch.arange(n, device=system.device)[:, None]
    pivots = []
    for k in range(n):
        pivots.append(augmented[k, k])
        row = augmented[k] / augmented[k, k]
        augmented = torch.where(rows == k, row, augmented - augmented[:, k : k + 1] * row)
    return augmented[:, n], (torch.stack(pivots) > 0).all()


def lm_start(pose: torch.Tensor) -> LmState:
    """A level's first state: evaluate `pose` [..., 4, 4] float64 first (any cost beats
    infinity); leading dimensions make a batch of independent solves (`lm_iterations`)."""
    batch, device = pose.shape[:-2], pose.device
    zero = torch.zeros(batch, dtype=torch.float64, device=device)
    count = torch.zeros(batch, dtype=torch.long, device=device)
    fit = Linearisation(
        torch.zeros(*batch, 6, 6, dtype=torch.float64, device=device),
        torch.zeros(*batch, 6, dtype=torch.float64, device=device),
        torch.full(batch, float("inf"), dtype=torch.float64, device=device),
        count,
        count.clone(),
        zero.float(),
        zero.float(),
    )
    # Distinct tensors: the compiled iteration guards on aliasing, and shared inputs would compile it
    # once more per level (eight compilations then stop compiling and run it eager).
    return LmState(pose, pose.clone(), torch.full_like(zero, INITIAL_DAMPING), fit)


def lm_iteration(state: LmState, source: SourcePoints, target: TargetMaps, params: AlignParams) -> LmState:
    """Evaluate the candidate; keep it if its cost is no higher (else keep the pose and raise the
    damping); propose the next candidate from the kept linearisation."""
    fit = linearise(state.candidate, source, target, params)
    accept = fit.cost <= state.fit.cost  # False for a NaN cost
    kept = Linearisation(*(torch.where(accept, new, old) for new, old in zip(fit, state.fit)))
    pose = torch.where(accept, state.candidate, state.pose)
    damping = torch.where(accept, state.damping * DAMPING_DOWN, state.damping * DAMPING_UP).clamp(*DAMPING_RANGE)
    candidate = se3_exp(damped_step(kept.hessian, kept.gradient, damping)) @ pose
    return LmState(pose, candidate, damping, kept)


AlignIteration = Callable[[LmState, SourcePoints, TargetMaps, AlignParams], LmState]


def lm_iterations(states: LmState, source: SourcePoints, target: TargetMaps, params: AlignParams) -> LmState:
    """`lm_iteration` over a batch of states (each field with a leading dimension: solves from
    several starts, `lm_start` of [S, 4, 4]) against one source and target: one kernel per
    operation for all of them. Compile this, not `lm_iteration` under vmap: a compiled function
    under vmap runs eager (dynamo refuses the transform)."""
    solves: LmState = torch.vmap(lm_iteration, in_dims=(0, None, None, None))(states, source, target, params)
    return solves


def solve_of(solves: LmState, index: int) -> LmState:
    """Solve `index` of a batch of solves (`lm_iterations`: each field with a leading dimension)."""
    state: LmState = tree_map(lambda field: field[index], solves)
    return state


class AlignKernels(NamedTuple):
    """The iteration from one start (`one`) and over a batch of starts (`batch`, `lm_iterations`),
    compiled apart where compiled (`make_kernels`)."""

    one: AlignIteration
    batch: AlignIteration


EAGER_ALIGN = AlignKernels(lm_iteration, lm_iterations)


def align(
    sources: Sequence[SourcePoints],
    targets: Sequence[TargetMaps],
    params: Sequence[AlignParams],
    schedule: Sequence[int],
    iteration: AlignIteration = lm_iteration,
    start: torch.Tensor | None = None,
) -> LmState:
    """Coarse to fine from the motion `start` [4, 4] float64 (default: the identity; [S, 4, 4]
    with `lm_iterations`: S solves at once). `sources`, `targets` and `params` hold one
    entry per pyramid level, finest first; `schedule` the iterations per level, coarsest first.
    Each level starts from the best pose of the one before -> the finest level's last state."""
    pose = torch.eye(4, dtype=torch.float64, device=sources[0].points.device) if start is None else start
    state = lm_start(pose)
    for level, iterations in zip(reversed(range(len(sources))), schedule):
        state = lm_start(state.pose)
        for _ in range(iterations):
            state = iteration(state, sources[level], targets[level], params[level])
    return state
