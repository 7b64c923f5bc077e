"""Pose graphs in g2o's text format (`EDGE_SE3:QUAT`), as g2o, GTSAM's `readG2o` and graph
viewers read them: a run's keyframe graph can be re-optimised or looked at with their tools.

One `VERTEX_SE3:QUAT id x y z qx qy qz qw` per node (its camera-to-world pose, metres) and one
`EDGE_SE3:QUAT i j x y z qx qy qz qw` followed by the 21 upper-triangular entries (row by row) of
the edge's 6x6 information per edge. g2o has no standard mark for a loop closure: the loop edges
are those whose nodes are not consecutive (|j - i| > 1, as `pose_graph.Edge.closes_loop`); the
edges here are plain.

Our information is ordered (rotation in radians, translation in metres), for a right perturbation
of `relative` (relative @ exp(xi)), as GTSAM's BetweenFactor<Pose3> takes it; g2o orders it
(translation, rotation), so it is permuted on writing, as GTSAM's `writeG2o` does and `readG2o`
undoes. (g2o's own EdgeSE3 measures the rotation error by the quaternion's vector part, about half
the angle, so g2o itself weighs a rotation a quarter as much as GTSAM reading the same file.)
Numbers are written as `repr` writes them, the shortest text that reads back to the same double.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from pipeline.geometry import rotmat_to_quat

F64 = torch.float64
G2O_ORDER = [3, 4, 5, 0, 1, 2]  # (translation, rotation) from our (rotation, translation); its own inverse


@dataclass(frozen=True)
class G2oEdge:
    """One relative-pose measurement between two nodes (their positions in `c2w`)."""

    first: int
    second: int
    relative: torch.Tensor  # [4, 4] float64 inv(c2w_first) @ c2w_second: camera `second` in camera `first`
    information: torch.Tensor  # [6, 6] float64, (rotation rad, translation m), right perturbation


def g2o_text(c2w: torch.Tensor, edges: Sequence[G2oEdge]) -> str:
    """Nodes `c2w` [K, 4, 4] float64 camera-to-world (metres) and `edges` as a g2o file's text."""
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
        raise ValueError(f"c2w must be [K, 4, 4], found {list(c2w.shape)}")
    nodes = c2w.shape[0]
    lines = [f"VERTEX_SE3:QUAT {k} {_pose(pose)}" for k, pose in enumerate(c2w.to("cpu", F64))]
    for edge in edges:
        if not (0 <= edge.first < nodes and 0 <= edge.second < nodes):
            raise ValueError(f"edge {edge.first}-{edge.second} names a node outside 0..{nodes - 1}")
        information = edge.information.to("cpu", F64)[G2O_ORDER][:, G2O_ORDER].tolist()
        upper = [information[i][j] for i in range(6) for j in range(i, 6)]
        lines.append(f"EDGE_SE3:QUAT {edge.first} {edge.second} {_pose(edge.relative)} {_numbers(upper)}")
    return "\n".join(lines) + "\n"


def _pose(pose: torch.Tensor) -> str:
    """[4, 4] rigid transform -> `x y z qx qy qz qw`."""
    pose = pose.to("cpu", F64)
    w, x, y, z = rotmat_to_quat(pose[:3, :3]).tolist()
    return _numbers([*pose[:3, 3].tolist(), x, y, z, w])


def _numbers(values: Sequence[float]) -> str:
    return " ".join(repr(float(v)) for v in values)
