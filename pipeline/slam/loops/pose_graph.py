"""The keyframe pose graph: keyframe poses as nodes, relative-pose measurements as edges, and its
optimisation with GTSAM (Levenberg-Marquardt; a robust kernel on loop edges).

Edges measure `relative` = inv(c2w_first) @ c2w_second, the camera of `second` in the camera of
`first`; their information matrices are for a right perturbation of it, relative @ exp(xi), xi =
(rotation in radians, translation in metres), as GTSAM's BetweenFactor<Pose3> takes them. The
first node is held fixed (the map's frame). A graph without a loop edge that spans more than one
keyframe is returned as it is: no loop, no change.

GTSAM is imported where the graph is optimised, so the rest of this module needs no extra.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.config import LoopConfig
from pipeline.geometry import invert_pose, motion_extent, skew

F64 = torch.float64
PRIOR_SIGMA = 1e-6  # radians and metres: the first node's prior (the result is re-anchored to it exactly)


@dataclass(frozen=True)
class Edge:
    """One relative-pose measurement between two nodes (positions in the graph)."""

    first: int
    second: int
    relative: torch.Tensor  # [4, 4] float64: camera `second` in camera `first`
    information: torch.Tensor  # [6, 6] float64, for a right perturbation (rotation, translation)
    loop: bool = False  # a loop closure (robust kernel) rather than odometry

    @property
    def closes_loop(self) -> bool:
        """A loop edge between keyframes that are not neighbours (one beside an odometry edge adds nothing)."""
        return self.loop and abs(self.second - self.first) > 1


@dataclass(frozen=True)
class PoseGraph:
    """Keyframe poses (oldest first) and the edges between them (`chained`), never changed in place."""

    c2w: torch.Tensor  # [K, 4, 4] float64 camera-to-world on the host
    edges: tuple[Edge, ...] = ()

    def __len__(self) -> int:
        return int(self.c2w.shape[0])


@dataclass(frozen=True)
class MotionSize:
    """How far a rigid motion moves: its translation and its rotation angle."""

    translation_m: float
    rotation_deg: float


@dataclass(frozen=True)
class GraphSolution:
    """The optimised poses and the fate of each loop edge."""

    c2w: torch.Tensor  # [K, 4, 4] float64 corrected camera-to-world (the input when nothing changed)
    kept: tuple[Edge, ...]  # loop edges the solution agrees with
    dropped: tuple[Edge, ...]  # loop edges it does not (residual over the limits): left out of it
    residuals: tuple[MotionSize, ...]  # of the kept loops, at the solution
    graph: PoseGraph  # the graph to keep: nodes at `c2w`, the dropped loops gone


def chained(c2w: torch.Tensor, odometry_information: torch.Tensor, loops: tuple[Edge, ...]) -> PoseGraph:
    """Nodes at `c2w` [K, 4, 4] float64, an odometry edge from each node to the next at the
    relative pose the nodes imply (of `odometry_information[k]` [6, 6] for the edge into node k),
    and the `loops`."""
    odometry = tuple(
        Edge(k - 1, k, invert_pose(c2w[k - 1]) @ c2w[k], odometry_information[k]) for k in range(1, len(c2w))
    )
    return PoseGraph(c2w, (*odometry, *loops))


def adjoint(pose: torch.Tensor) -> torch.Tensor:
    """[4, 4] rigid T -> [6, 6] Ad_T with exp(Ad_T xi) = T exp(xi) T^-1, xi = (rotation, translation)."""
    rotation, translation = pose[:3, :3], pose[:3, 3]
    top = torch.cat([rotation, torch.zeros_like(rotation)], dim=1)
    bottom = torch.cat([skew(translation) @ rotation, rotation], dim=1)
    return torch.cat([top, bottom])


def alignment_information(hessian: torch.Tensor, motion: torch.Tensor, scale: float) -> torch.Tensor:
    """An edge's information [6, 6] from a dense alignment's normal equations `hessian` [6, 6]
    (`Linearisation.hessian`: normalised residuals, a left perturbation exp(xi) @ motion of the
    solved `motion` [4, 4], source camera -> target camera), times `scale`. The measured relative
    pose is then `motion` itself (target = first, source = second), and exp(xi_left) @ motion =
    motion @ exp(xi_right) with xi_left = Ad(motion) xi_right, so the information becomes
    Ad^T H Ad. `scale` < 1 because neighbouring pixels' errors are not independent."""
    ad = adjoint(motion.to("cpu", F64))
    information = ad.T @ hessian.to("cpu", F64) @ ad
    return scale * (information + information.T) / 2


def fixed_information(sigma_m: float, sigma_deg: float) -> torch.Tensor:
    """A diagonal information [6, 6] of standard deviations `sigma_deg` per rotation axis and
    `sigma_m` per translation axis (keyframes tracked without normal equations: adam)."""
    sigma_rad = torch.full((3,), sigma_deg, dtype=F64).deg2rad()
    sigmas = torch.cat([sigma_rad, torch.full((3,), sigma_m, dtype=F64)])
    return torch.diag(sigmas**-2)


def motion_size(motion: torch.Tensor) -> MotionSize:
    """Of a rigid motion [4, 4]."""
    translation_m, rotation_deg = motion_extent(motion).tolist()
    return MotionSize(translation_m, rotation_deg)


def edge_residual(c2w: torch.Tensor, edge: Edge) -> MotionSize:
    """How far the solution's poses [K, 4, 4] are from an edge: inv(measured) @ their relative pose."""
    return motion_size(invert_pose(edge.relative) @ invert_pose(c2w[edge.first]) @ c2w[edge.second])


def _within(residual: MotionSize, config: LoopConfig) -> bool:
    return (
        residual.translation_m <= config.max_loop_residual_m and residual.rotation_deg <= config.max_loop_residual_deg
    )


def _excess(residual: MotionSize, config: LoopConfig) -> float:
    return max(
        residual.translation_m / config.max_loop_residual_m, residual.rotation_deg / config.max_loop_residual_deg
    )


def optimise(graph: PoseGraph, config: LoopConfig) -> GraphSolution:
    """The poses that best fit all edges, loops under a Cauchy kernel (`loop_kernel_width`, in whitened
    units), solved from the least-squares optimum (every loop as a plain Gaussian edge): from the
    drifted estimates themselves a real loop that drifted far (the cabinet's: 2 m and 44 degrees,
    hundreds of its sigmas) gets next to no weight under the kernel, the solve barely moves and the
    loop is dropped; from the least-squares optimum it is kept and the keyframes come back from 207
    to 65 cm of error (bench/NOTES.md, Change 24). A loop the solution still misses by more than
    `max_loop_residual_m` or `max_loop_residual_deg` is dropped (the worst first) and the graph
    solved again without it: a false loop bends the whole trajectory, so it goes even if the kernel
    would have tamed it. Without a loop edge that closes a loop (and after dropping them all) -> the
    input poses."""
    odometry = [edge for edge in graph.edges if not edge.loop]
    loops = [edge for edge in graph.edges if edge.closes_loop]
    dropped: list[Edge] = []
    c2w, residuals = graph.c2w, []
    while loops:
        c2w = _solve(_solve(graph.c2w, odometry, loops, config, robust=False), odometry, loops, config)
        residuals = [edge_residual(c2w, edge) for edge in loops]
        if all(_within(residual, config) for residual in residuals):
            break
        worst = max(range(len(loops)), key=lambda k: _excess(residuals[k], config))
        dropped.append(loops.pop(worst))
        c2w, residuals = graph.c2w, []
    kept = PoseGraph(c2w, tuple(edge for edge in graph.edges if not any(edge is gone for gone in dropped)))
    return GraphSolution(c2w, tuple(loops), tuple(dropped), tuple(residuals), kept)


def _solve(
    c2w: torch.Tensor, odometry: list[Edge], loops: list[Edge], config: LoopConfig, robust: bool = True
) -> torch.Tensor:
    """Levenberg-Marquardt from the poses [K, 4, 4] (loops under the Cauchy kernel where
    `robust`) -> the solution, re-anchored so that the first node is exactly where it was."""
    import gtsam

    factors = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for key, pose in enumerate(c2w.numpy()):
        initial.insert(key, gtsam.Pose3(pose))
    factors.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)))
    kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(config.loop_kernel_width)
    for edge in odometry + loops:
        gaussian = gtsam.noiseModel.Gaussian.Information(edge.information.numpy())
        noise = gtsam.noiseModel.Robust.Create(kernel, gaussian) if edge.loop and robust else gaussian
        factors.add(gtsam.BetweenFactorPose3(edge.first, edge.second, gtsam.Pose3(edge.relative.numpy()), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(factors, initial, params).optimize()
    solved = torch.stack([torch.from_numpy(result.atPose3(key).matrix()) for key in range(len(c2w))])
    anchored = c2w[0] @ invert_pose(solved[0]) @ solved
    return torch.cat([c2w[:1], anchored[1:]])
