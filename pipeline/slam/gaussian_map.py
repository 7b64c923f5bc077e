"""The Gaussian map: parameters as leaf tensors, created from RGB-D pixels, grown and pruned."""

from __future__ import annotations

import math
from dataclasses import fields

import torch

from pipeline.config import GaussianConfig
from pipeline.geometry import backproject, pixel_grid
from pipeline.render.types import Gaussians


def seed_gaussians(
    color: torch.Tensor,
    depth: torch.Tensor,
    intrinsics: torch.Tensor,
    c2w: torch.Tensor,
    mask: torch.Tensor,
    config: GaussianConfig,
) -> Gaussians:
    """One Gaussian per pixel of `mask` [H, W] (SplaTAM's initialisation).

    colour [H, W, 3] in [0, 1], depth [H, W] metres, camera-to-world [4, 4]. Mean: the
    back-projected pixel centre; colour: the pixel's; identity rotation; opacity
    `config.seed_opacity`; scale: `config.seed_scale` footprints of the pixel (depth / mean
    focal length), repeated when anisotropic. SplaTAM's seeds (one footprint, opacity 0.5)
    overlap their neighbours so much that a render of them composites nearer neighbours first
    and its depth comes out short on slanted surfaces, by an amount that follows the pixel's
    footprint: the pull on a frame halves with each doubling of the resolution (0.26 cm on a
    real frame at 640x480; bench/NOTES.md, Change 40).
    """
    u, v = pixel_grid(depth.shape[0], depth.shape[1], depth.device)
    pixels = mask.reshape(-1).nonzero()[:, 0]  # one read-back of the count, shared by every gather
    z = depth.reshape(-1)[pixels]
    means = backproject(u.reshape(-1)[pixels], v.reshape(-1)[pixels], z, intrinsics, c2w)
    n = means.shape[0]
    focal = (intrinsics[0, 0] + intrinsics[1, 1]) / 2
    log_scale = torch.log(config.seed_scale * z / focal)[:, None]
    axes = 1 if config.isotropic else 3
    quats = torch.zeros(n, 4, device=depth.device)
    quats[:, 0] = 1.0
    return Gaussians(
        means=means,
        quats=quats,
        log_scales=log_scale.expand(-1, axes).contiguous(),
        opacity_logits=torch.full((n,), math.log(config.seed_opacity / (1 - config.seed_opacity)), device=depth.device),
        colors=color.reshape(-1, 3)[pixels],
    )


PARAMETER_NAMES = tuple(f.name for f in fields(Gaussians))


def as_leaves(gaussians: Gaussians) -> Gaussians:
    """Detached copies that require gradients: the parameters an optimiser updates."""
    return Gaussians(*(getattr(gaussians, name).detach().clone().requires_grad_(True) for name in PARAMETER_NAMES))


def detached(gaussians: Gaussians) -> Gaussians:
    """A view without gradients (for tracking and evaluation renders)."""
    return Gaussians(*(getattr(gaussians, name).detach() for name in PARAMETER_NAMES))


def copied(gaussians: Gaussians, device: torch.device | str | None = None) -> Gaussians:
    """Detached copies (on `device`, default where they are): a snapshot SLAM's later in-place
    updates do not touch."""
    return Gaussians(*(getattr(gaussians, n).detach().to(device, copy=True) for n in PARAMETER_NAMES))


def concatenate(a: Gaussians, b: Gaussians) -> Gaussians:
    return Gaussians(*(torch.cat([getattr(a, n).detach(), getattr(b, n).detach()]) for n in PARAMETER_NAMES))


def gathered(gaussians: Gaussians, positions: torch.Tensor) -> Gaussians:
    """The Gaussians at `positions` [M] (int64), detached."""
    return Gaussians(*(getattr(gaussians, n).detach()[positions] for n in PARAMETER_NAMES))


def most_opaque(gaussians: Gaussians, count: int) -> torch.Tensor | None:
    """Positions [count] of the `count` most opaque Gaussians (None when there are no more than that)."""
    if len(gaussians) <= count:
        return None
    return torch.topk(gaussians.opacity_logits.detach(), count, sorted=False).indices


def prune_mask(gaussians: Gaussians, min_opacity: float, max_scale: float) -> torch.Tensor:
    """[N] bool of the Gaussians to keep: opacity >= min_opacity and largest scale <= max_scale."""
    opacity = torch.sigmoid(gaussians.opacity_logits)
    largest = torch.exp(gaussians.log_scales).amax(-1)
    return (opacity >= min_opacity) & (largest <= max_scale)
