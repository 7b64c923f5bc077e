"""A small mapping scene shared by the CPU and GPU mapping tests: a textured plane and three
keyframes that see it (tests/ is on the path of every test module, through its conftest)."""

from __future__ import annotations

import torch

from pipeline.config import GaussianConfig, RenderConfig
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians, make_renderer
from pipeline.slam.keyframes import Keyframe

CPU = torch.device("cpu")
K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])  # pixels, for 32 x 24 images


def plane_scene() -> tuple[Gaussians, list[Keyframe]]:
    """A textured plane 2 m ahead and one Gaussian behind the cameras, which no view sees."""
    v, u = torch.meshgrid(torch.arange(24) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    z = torch.full_like(u, 2.0)
    means = torch.stack([(u - 16) / 40 * z, (v - 12) / 40 * z, z], -1).reshape(-1, 3)
    means = torch.cat([means, torch.tensor([[0.0, 0.0, -3.0]])])
    n = len(means)
    colors = 0.5 + 0.4 * torch.sin(means[:, :1] * 9 + torch.tensor([0.0, 1.0, 2.0]))
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    gaussians = Gaussians(means, quats, torch.full((n, 1), -3.6), torch.full((n,), 2.0), colors)
    renderer = make_renderer(RenderConfig(), GaussianConfig(), CPU)
    keyframes = []
    for i, dx in enumerate((0.0, 0.05, -0.05)):
        c2w = torch.eye(4)
        c2w[0, 3] = dx
        out = renderer(gaussians, Camera(invert_pose(c2w), K, 32, 24))
        keyframes.append(Keyframe.of(i, (out.color * 0.8).clamp(0, 1), out.depth * 1.02, c2w))
    return gaussians, keyframes
