"""The pose graph as a g2o file: GTSAM's own reader gives back our poses, measurements and
information (in our order, rotation then translation), so g2o's and GTSAM's tools read it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.geometry import invert_pose, se3_exp
from pipeline.io.files.g2o import G2O_ORDER, G2oEdge, g2o_text

F64 = torch.float64


def _graph(generator: torch.Generator) -> tuple[torch.Tensor, list[G2oEdge]]:
    """4 nodes along a path, 3 odometry edges and a loop edge 3 -> 0, each of a random SPD information."""
    twists = torch.randn(4, 6, generator=generator, dtype=F64)
    c2w = torch.stack([se3_exp(twist) for twist in twists])
    edges = []
    for first, second in [(0, 1), (1, 2), (2, 3), (3, 0)]:
        a = torch.randn(6, 6, generator=generator, dtype=F64)
        relative = invert_pose(c2w[first]) @ c2w[second]
        edges.append(G2oEdge(first, second, relative, a @ a.T + 0.5 * torch.eye(6, dtype=F64)))
    return c2w, edges


def test_gtsam_reads_back_the_graph_written(tmp_path: Path) -> None:
    gtsam = pytest.importorskip("gtsam", reason="loop closure's extra: pip install -e '.[loops]'")
    c2w, edges = _graph(torch.Generator().manual_seed(0))
    path = tmp_path / "graph.g2o"
    path.write_text(g2o_text(c2w, edges))
    assert path.read_text() == g2o_text(c2w, edges)
    graph, values = gtsam.readG2o(str(path), True)
    assert values.size() == 4 and graph.size() == 4
    for k in range(4):
        np.testing.assert_allclose(values.atPose3(k).matrix(), c2w[k].numpy(), rtol=0, atol=1e-9)
    for index, edge in enumerate(edges):
        factor = graph.at(index)
        assert isinstance(factor, gtsam.BetweenFactorPose3) and list(factor.keys()) == [edge.first, edge.second]
        np.testing.assert_allclose(factor.measured().matrix(), edge.relative.numpy(), rtol=0, atol=1e-9)
        information = factor.noiseModel().information()  # GTSAM's order: rotation, translation, as ours
        np.testing.assert_allclose(information, edge.information.numpy(), rtol=1e-9, atol=1e-9)


def test_the_text_is_one_line_per_node_and_edge_with_exact_numbers() -> None:
    c2w, edges = _graph(torch.Generator().manual_seed(1))
    lines = g2o_text(c2w, edges).splitlines()
    assert [line.split()[0] for line in lines] == ["VERTEX_SE3:QUAT"] * 4 + ["EDGE_SE3:QUAT"] * 4
    vertex, edge = lines[2].split(), lines[-1].split()
    assert len(vertex) == 9 and [float(v) for v in vertex[2:5]] == c2w[2, :3, 3].tolist()  # repr: exact
    assert len(edge) == 3 + 7 + 21 and edge[1:3] == ["3", "0"]
    information = edges[-1].information[G2O_ORDER][:, G2O_ORDER]  # g2o's order: translation, rotation
    assert [float(v) for v in edge[10:16]] == information[0].tolist()


def test_an_edge_to_a_missing_node_is_refused() -> None:
    c2w, edges = _graph(torch.Generator().manual_seed(2))
    with pytest.raises(ValueError, match="outside 0..3"):
        g2o_text(c2w, [*edges, G2oEdge(0, 4, edges[0].relative, edges[0].information)])
