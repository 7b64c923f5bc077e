"""Which solver optimises the keyframe pose graph: GTSAM (what pose_graph.optimise uses) against
PyPose's Levenberg-Marquardt (dense Jacobians by autograd), on the CPU. PyPose minimises the
plain least squares (no kernel on the loops), GTSAM the graph as optimise builds it.

Graphs: K keyframes round a 1 m circle, odometry with a yaw bias and translation noise (as
tests/slam/test_pose_graph.py builds them), two loop edges with the true relative poses, the
same information everywhere (sigma 1 cm, 0.5 degrees). Reported per solver and size: seconds
per optimisation (after one warm-up), keyframe ATE before and after, iterations.

    python bench/pose_graph_solvers.py [K ...]   (default 35 200 1000; PyPose up to 200)
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from slam.test_pose_graph import CONFIG, ate, chain, circle, drifted, loop_edge, with_loop  # noqa: E402

from pipeline.geometry import invert_pose, skew  # noqa: E402
from pipeline.slam.loops.pose_graph import PoseGraph, optimise  # noqa: E402

F64 = torch.float64
DENSE_LIMIT = 200  # keyframes: past this PyPose's dense 6K x 6E Jacobian takes minutes


def se3_log(pose: torch.Tensor) -> torch.Tensor:
    """[..., 4, 4] -> twists [..., 6] (rotation, translation), inverse of se3_exp away from pi."""
    rotation, translation = pose[..., :3, :3], pose[..., :3, 3]
    cosine = ((rotation.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1 + 1e-12, 1 - 1e-12)
    theta = torch.arccos(cosine)
    vee = torch.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        dim=-1,
    )
    small = theta < 1e-6
    factor = torch.where(small, 0.5 + theta**2 / 12, theta / (2 * torch.sin(theta).clamp(min=1e-12)))
    omega = factor[..., None] * vee
    w = skew(omega)
    eye = torch.eye(3, dtype=pose.dtype)
    t2 = theta.clamp(min=1e-12) ** 2
    b = torch.where(
        small, 1 / 12 + t2 / 720, (1 - theta * torch.sin(theta) / (2 * (1 - torch.cos(theta)).clamp(min=1e-24))) / t2
    )
    inverse_v = eye - 0.5 * w + b[..., None, None] * (w @ w)
    return torch.cat([omega, (inverse_v @ translation[..., None])[..., 0]], dim=-1)


def residuals(poses: torch.Tensor, graph: PoseGraph) -> torch.Tensor:
    """Whitened residuals [6E + 6] of every edge and the first node's prior."""
    rows = []
    for edge in graph.edges:
        error = se3_log(invert_pose(edge.relative) @ invert_pose(poses[edge.first]) @ poses[edge.second])
        rows.append(torch.linalg.cholesky(edge.information).T @ error)
    rows.append(1e6 * se3_log(invert_pose(graph.c2w[0]) @ poses[0]))
    return torch.cat(rows)


def pypose_lm(graph: PoseGraph, iterations: int = 10) -> tuple[torch.Tensor, int]:
    import pypose as pp

    class Graph(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.nodes = pp.Parameter(pp.mat2SE3(graph.c2w))

        def forward(self) -> torch.Tensor:
            return residuals(self.nodes.matrix(), graph)

    model = Graph()
    optimiser = pp.optim.LM(model, solver=pp.optim.solver.Cholesky(), strategy=pp.optim.strategy.TrustRegion())
    last = float("inf")
    for step in range(iterations):
        loss = float(optimiser.step(input=()))
        if abs(last - loss) < 1e-9 * max(loss, 1.0):
            return model.nodes.matrix().detach(), step + 1
        last = loss
    return model.nodes.matrix().detach(), iterations


def gtsam(graph: PoseGraph) -> tuple[torch.Tensor, int]:
    return optimise(graph, CONFIG).c2w, -1


def timed(solve, graph: PoseGraph) -> tuple[float, torch.Tensor, int]:
    solve(graph)
    start = time.perf_counter()
    c2w, steps = solve(graph)
    return time.perf_counter() - start, c2w, steps


def main(sizes: list[int]) -> None:
    torch.set_num_threads(1)
    for count in sizes:
        truth = circle(count)
        estimate = drifted(truth, 0.3 / count)
        graph = with_loop(with_loop(chain(estimate), loop_edge(truth, 0, count - 1)), loop_edge(truth, 1, count - 2))
        solvers = {"gtsam": gtsam}
        if count <= DENSE_LIMIT:
            solvers["pypose"] = pypose_lm
        row = {"keyframes": count, "ate_before_cm": round(100 * ate(estimate, truth), 2)}
        for name, solve in solvers.items():
            seconds, c2w, steps = timed(solve, graph)
            row[name] = {
                "seconds": round(seconds, 4),
                "ate_after_cm": round(100 * ate(c2w, truth), 3),
                "iterations": steps,
            }
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main([int(x) for x in sys.argv[1:]] or [35, 200, 1000])
