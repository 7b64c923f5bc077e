"""Image losses and measures; images are [H, W, C] or [H, W] tensors."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def _gaussian_kernel(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW, device=device, dtype=dtype) - SSIM_WINDOW // 2
    g = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return g / g.sum()


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of two [H, W, 3] images in [0, 1] (11x11 Gaussian window, sigma 1.5) -> [H, W].

    The five local statistics (means, second moments, cross moment) of all channels are blurred
    together: one depthwise convolution per axis instead of ten.
    """
    channels = a.shape[-1]
    x, y = a.permute(2, 0, 1), b.permute(2, 0, 1)  # [C, H, W]
    stack = torch.cat([x, y, x * x, y * y, x * y])[None]  # [1, 5C, H, W]
    g = _gaussian_kernel(a.device, a.dtype)
    groups = 5 * channels
    pad = SSIM_WINDOW // 2
    blurred = F.conv2d(F.pad(stack, (pad, pad, 0, 0)), g.view(1, 1, 1, -1).expand(groups, 1, 1, -1), groups=groups)
    blurred = F.conv2d(F.pad(blurred, (0, 0, pad, pad)), g.view(1, 1, -1, 1).expand(groups, 1, -1, 1), groups=groups)
    mu_a, mu_b, a2, b2, ab = blurred[0].split(channels)
    sigma_a, sigma_b, sigma_ab = a2 - mu_a**2, b2 - mu_b**2, ab - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_a * mu_b + c1) * (2 * sigma_ab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (sigma_a + sigma_b + c2))
    return value.mean(0)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return ssim_map(a, b).mean()


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1] over the pixels of `mask` [H, W]."""
    mse = ((a - b) ** 2)[mask].mean().item()
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)
