"""Random Gaussian scenes inside a camera's view, shared by the GPU tests and bench/parity.py."""

from __future__ import annotations

import torch

from pipeline.geometry import quat_to_rotmat
from pipeline.render.types import Gaussians, RenderOutput

# Tolerances on relative L2 error ||gsplat - reference|| / ||reference||, chosen before the run:
# float32 arithmetic in a different order (and __expf on the GPU) lands far under 1e-4 for the
# images; gradients pass through sums over many pixels and get 1e-3. The finite-difference check
# of the smooth reference runs in float64: 1e-4.
TOLERANCE = {"image": 1e-4, "grad": 1e-3, "fd": 1e-4}


def random_pose(generator: torch.Generator, device: torch.device) -> torch.Tensor:
    """A random camera-to-world [4, 4]: any rotation, translation within 2 m."""
    quat = torch.randn(4, generator=generator)
    c2w = torch.eye(4)
    c2w[:3, :3] = quat_to_rotmat(quat)
    c2w[:3, 3] = (torch.rand(3, generator=generator) - 0.5) * 4
    return c2w.to(device)


def random_scene(
    n: int, isotropic: bool, c2w: torch.Tensor, k: torch.Tensor, width: int, height: int, generator: torch.Generator
) -> Gaussians:
    """n Gaussians inside the camera's view (depth 1 to 6 m), sizes from sub-pixel to ~20 px."""
    device = c2w.device
    u = torch.rand(n, generator=generator) * width * 1.2 - 0.1 * width
    v = torch.rand(n, generator=generator) * height * 1.2 - 0.1 * height
    z = 1 + 5 * torch.rand(n, generator=generator)
    cam = torch.stack([(u - k[0, 2].cpu()) / k[0, 0].cpu() * z, (v - k[1, 2].cpu()) / k[1, 1].cpu() * z, z], -1).to(
        device
    )
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]
    pixels = 0.3 + 20 * torch.rand(n, 1 if isotropic else 3, generator=generator) ** 2
    log_scales = torch.log(pixels.to(device) * z[:, None].to(device) / k[0, 0])
    return Gaussians(
        means=means,
        quats=torch.randn(n, 4, generator=generator).to(device),
        log_scales=log_scales,
        opacity_logits=(torch.randn(n, generator=generator) * 2).to(device),
        colors=torch.rand(n, 3, generator=generator).to(device),
    )


def leaves(g: Gaussians) -> Gaussians:
    return Gaussians(
        *(t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.colors))
    )


def loss_of(out: RenderOutput, weights: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> torch.Tensor:
    wc, wd, ws = weights
    return (out.color * wc).sum() + (out.depth * wd).sum() + (out.silhouette * ws).sum()


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double(), b.detach().double()
    return float(torch.linalg.norm(a - b) / torch.linalg.norm(b).clamp(min=1e-30))
