"""Image losses and measures; images are [H, W, C] or [H, W] tensors."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
# The normalised 1D Gaussian window as Python floats: constants the compiler folds into its kernel.
_SSIM_TAPS = [math.exp(-((k - SSIM_WINDOW // 2) ** 2) / (2 * SSIM_SIGMA**2)) for k in range(SSIM_WINDOW)]
SSIM_TAPS = [t / sum(_SSIM_TAPS) for t in _SSIM_TAPS]


def _blur(x: torch.Tensor, dim: int) -> torch.Tensor:
    """The Gaussian window along `dim` with zero padding, as a weighted sum of shifted views.

    Written as element-wise arithmetic rather than a convolution so that `torch.compile` fuses the
    products, both blur passes and the SSIM formula (forward and backward) into a few kernels; a
    depthwise convolution is a separate library call that the compiler cannot fuse.
    """
    pad = SSIM_WINDOW // 2
    size = x.shape[dim]
    widths = [0, 0] * (x.dim() - 1 - dim) + [pad, pad]
    padded = F.pad(x, widths)
    blurred = SSIM_TAPS[0] * padded.narrow(dim, 0, size)
    for k, tap in enumerate(SSIM_TAPS[1:], start=1):
        blurred = blurred + tap * padded.narrow(dim, k, size)
    return blurred


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of two [H, W, 3] images in [0, 1] (11x11 Gaussian window, sigma 1.5) -> [H, W].

    The window is separable: blurred along rows, then columns; the five local statistics
    (means, second moments, cross moment) of all channels are blurred together.
    """
    channels = a.shape[-1]
    stack = torch.cat([a, b, a * a, b * b, a * b], dim=-1)  # [H, W, 5C]
    blurred = _blur(_blur(stack, 1), 0)
    mu_a, mu_b, a2, b2, ab = blurred.split(channels, dim=-1)
    sigma_a, sigma_b, sigma_ab = a2 - mu_a**2, b2 - mu_b**2, ab - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_a * mu_b + c1) * (2 * sigma_ab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (sigma_a + sigma_b + c2))
    return value.mean(-1)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return ssim_map(a, b).mean()


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1] over the pixels of `mask` [H, W]."""
    mse = ((a - b) ** 2)[mask].mean().item()
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)
