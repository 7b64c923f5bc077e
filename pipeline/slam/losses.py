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
    """Per-pixel SSIM of two [H, W, 3] images in [0, 1] (11x11 Gaussian window, sigma 1.5) -> [H, W]."""
    channels = a.shape[-1]
    x = torch.stack([a.permute(2, 0, 1), b.permute(2, 0, 1)])  # [2, C, H, W]
    g = _gaussian_kernel(a.device, a.dtype)
    kx = g.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    ky = g.view(1, 1, -1, 1).expand(channels, 1, -1, 1)

    def blur(img: torch.Tensor) -> torch.Tensor:
        pad = SSIM_WINDOW // 2
        img = F.conv2d(F.pad(img, (pad, pad, 0, 0), mode="constant"), kx, groups=channels)
        return F.conv2d(F.pad(img, (0, 0, pad, pad), mode="constant"), ky, groups=channels)

    mu = blur(x)
    mu_a, mu_b = mu[0], mu[1]
    sigma_a = blur(x[:1] * x[:1])[0] - mu_a**2
    sigma_b = blur(x[1:] * x[1:])[0] - mu_b**2
    sigma_ab = blur(x[:1] * x[1:])[0] - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_a * mu_b + c1) * (2 * sigma_ab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (sigma_a + sigma_b + c2))
    return value.mean(0)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return ssim_map(a, b).mean()


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1] over the pixels of `mask` [H, W]."""
    mse = ((a - b) ** 2)[mask].mean().item()
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)
