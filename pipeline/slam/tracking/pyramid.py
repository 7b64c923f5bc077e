"""Image pyramids of RGB-D frames for coarse-to-fine alignment.

Each level halves the size by averaging 2x2 blocks (an odd last row or column is dropped), so a
pixel centre at level l+1 sits at the centre of its block and, with pixel (u, v) centred at
(u + 0.5, v + 0.5), the intrinsics simply halve: fx, fy, cx, cy / 2.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.errors import UserError

LUMA = (0.299, 0.587, 0.114)  # Rec. 601 weights of R, G, B
MIN_COARSE_SIZE = 4  # pixels: the coarsest level's shorter side may not be smaller
EDGE_SLOPE = 6.0  # neighbours further apart in depth than this many pixel footprints: a depth edge


@dataclass(frozen=True)
class RgbdLevel:
    """One level of a pyramid."""

    intensity: torch.Tensor  # [h, w] in [0, 1]
    depth: torch.Tensor  # [h, w] metres, 0 = invalid
    intrinsics: torch.Tensor  # [3, 3] pixels at this level


def intensity(color: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] RGB in [0, 1] -> luma [H, W]."""
    r, g, b = color.unbind(-1)
    return LUMA[0] * r + LUMA[1] * g + LUMA[2] * b


def _blocks(image: torch.Tensor) -> torch.Tensor:
    """[H, W] -> [H // 2, W // 2, 4]: the 2x2 block of every pixel of the next level."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    return image[: 2 * h, : 2 * w].reshape(h, 2, w, 2).permute(0, 2, 1, 3).reshape(h, w, 4)


def halve_image(image: torch.Tensor) -> torch.Tensor:
    """[H, W] -> [H // 2, W // 2], the mean of each 2x2 block."""
    return _blocks(image).mean(-1)


def same_surface(a: torch.Tensor, b: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
    """Whether depths a and b (metres) of neighbouring pixels lie on one surface: they differ by
    at most EDGE_SLOPE pixel footprints (depth / focal length in pixels), so the surface between
    them turns less than ~80 degrees away from the view."""
    return (a - b).abs() <= EDGE_SLOPE * torch.minimum(a, b) / focal


def halve_depth(depth: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
    """[H, W] metres (0 = invalid), focal length [] in pixels -> [H // 2, W // 2]: the mean of
    each block's valid depths; 0 where a block has none or spans a depth edge (the mean would be
    a point on neither surface)."""
    blocks = _blocks(depth)
    valid = blocks > 0
    count = valid.sum(-1)
    mean = blocks.sum(-1) / count.clamp(min=1)
    highest = blocks.amax(-1)
    lowest = torch.where(valid, blocks, highest[..., None]).amin(-1)
    keep = (count > 0) & same_surface(highest, lowest, focal)
    return torch.where(keep, mean, torch.zeros_like(mean))


def halve_intrinsics(intrinsics: torch.Tensor) -> torch.Tensor:
    """[3, 3] -> the intrinsics of the half-size image (fx, fy, cx, cy halved)."""
    return torch.cat([intrinsics[:2] * 0.5, intrinsics[2:]])  # no host-to-device copy: capturable


def check_pyramid_fits(levels: int, height: int, width: int) -> None:
    """A UserError when `levels` halvings would leave fewer than MIN_COARSE_SIZE pixels."""
    coarsest = min(height, width) >> (levels - 1)
    if coarsest < MIN_COARSE_SIZE:
        raise UserError(
            f"tracking.align_iters asks for {levels} pyramid levels: a {width}x{height} frame leaves "
            f"{coarsest} pixels at the coarsest (at least {MIN_COARSE_SIZE}); use fewer levels"
        )


def rgbd_pyramid(gray: torch.Tensor, depth: torch.Tensor, intrinsics: torch.Tensor, levels: int) -> list[RgbdLevel]:
    """Intensity [H, W], depth [H, W] metres and intrinsics [3, 3] -> `levels` levels, finest first."""
    pyramid = [RgbdLevel(gray, depth, intrinsics)]
    for _ in range(levels - 1):
        last = pyramid[-1]
        focal = torch.minimum(last.intrinsics[0, 0], last.intrinsics[1, 1])
        pyramid.append(
            RgbdLevel(halve_image(last.intensity), halve_depth(last.depth, focal), halve_intrinsics(last.intrinsics))
        )
    return pyramid
