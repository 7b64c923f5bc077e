"""Where the map needs new Gaussians after tracking a frame."""

from __future__ import annotations

import torch

from pipeline.config import DensifyConfig


def densify_mask(
    silhouette: torch.Tensor, render_depth: torch.Tensor, depth: torch.Tensor, config: DensifyConfig
) -> torch.Tensor:
    """[H, W] bool: valid-depth pixels the map does not explain.

    Either the map barely covers the pixel (silhouette < threshold), or the rendered surface
    lies behind the measured one by more than `depth_error_factor` x the median depth error
    (the median over valid-depth pixels; computed on the device without reading anything back:
    NaN, and so no "behind" pixels, when none is valid).
    """
    valid = depth > 0
    error = (render_depth - depth).abs()
    median = torch.where(valid, error, torch.nan).nanmedian()
    uncovered = silhouette < config.silhouette_threshold
    behind = (render_depth > depth) & (error > config.depth_error_factor * median)
    return (uncovered | behind) & valid
