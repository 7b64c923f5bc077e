"""Tile intersections at a fixed capacity: what gsplat's `isect_tiles` computes, without reading
the number of intersections back to the host.

gsplat sizes its intersection buffers from that number (`cum_tiles_per_gauss[-1].item()`), so
every render waits for the GPU and none can be recorded as a CUDA graph. Here the buffers have a
capacity chosen on the host and every entry past the true count is padding: its key names a
phantom tile in an extra row of tiles below the image, so it sorts after every real entry and
the rasteriser skips it (that tile is masked: `phantom_tile_mask`). The true count stays on the
device (`TileIntersections.count`); the caller reads it when it reads anything else, and grows
the capacity when the count passed it (`TileIntersections.overflowed`).

Keys are gsplat's: image id | tile id | depth bits (the float's bits: positive depths sort as
integers), sorted stably, so that the sorted entries equal gsplat's wherever the count fits.
Plain tensor functions: they run on any device (the CPU tests check them against a direct
construction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pipeline.render.intersect_kernel import intersect_kernel

INTERSECTION_QUANTUM = 1 << 16  # a fixed-capacity render's first capacity, and the step it grows by
CAPACITY_HEADROOM = 1.5  # a grown capacity holds this many times the largest count seen


def grown_capacity(count: int, quantum: int) -> int:
    """The capacity for `count` intersections with headroom, in whole steps of `quantum`."""
    return max(quantum, math.ceil(CAPACITY_HEADROOM * count / quantum) * quantum)


@dataclass(frozen=True)
class TileGrid:
    """The tiles of `images` images of `width` x `height` pixels, plus one phantom row below them."""

    images: int
    width: int  # pixels
    height: int
    tile_size: int = 16

    @property
    def tiles_x(self) -> int:
        return math.ceil(self.width / self.tile_size)

    @property
    def tiles_y(self) -> int:
        """Rows of real tiles (the phantom row comes after them)."""
        return math.ceil(self.height / self.tile_size)

    @property
    def tiles_per_image(self) -> int:
        """Tiles of one image with its phantom row: what the keys and the offsets count."""
        return self.tiles_x * (self.tiles_y + 1)

    @property
    def tile_bits(self) -> int:
        return int(math.floor(math.log2(self.tiles_per_image))) + 1

    @property
    def image_bits(self) -> int:
        return int(math.floor(math.log2(self.images))) + 1

    @property
    def padding_key(self) -> int:
        """The key of a padded entry: the last image's last phantom tile, at the largest depth bits."""
        tile = self.tiles_per_image - 1
        return ((self.images - 1) << (32 + self.tile_bits)) | (tile << 32) | 0xFFFFFFFF


@dataclass(frozen=True)
class TileIntersections:
    keys: torch.Tensor  # [capacity] int64, sorted: image | tile | depth bits; padding at the end
    flatten_ids: torch.Tensor  # [capacity] int32, image * N + gaussian of each entry (0 for padding)
    count: torch.Tensor  # [] int64 on the device: the true number of intersections

    @property
    def capacity(self) -> int:
        return self.keys.shape[0]

    def overflowed(self) -> torch.Tensor:
        """[] bool on the device: entries were lost (the render is wrong; grow the capacity)."""
        return self.count > self.capacity


def tile_ranges(means2d: torch.Tensor, radii: torch.Tensor, grid: TileGrid) -> tuple[torch.Tensor, torch.Tensor]:
    """Each projected Gaussian's tiles, as gsplat's `intersect_tile` kernel bounds them.

    means2d [I, N, 2] pixels, radii [I, N, 2] int pixels (0: not drawn) -> (first [I, N, 2]
    inclusive, end [I, N, 2] exclusive) tile coordinates (x, y), int64, clamped to the real tiles.
    """
    size = float(grid.tile_size)
    centre = means2d.detach() / size
    reach = radii.to(centre.dtype) / size
    first = _clamped_to_grid(torch.floor(centre - reach), grid)
    end = _clamped_to_grid(torch.ceil(centre + reach), grid)
    drawn = (radii > 0).all(-1, keepdim=True)
    return first, torch.where(drawn, end, first)


def _clamped_to_grid(tiles: torch.Tensor, grid: TileGrid) -> torch.Tensor:
    """[..., 2] tile coordinates (x, y) clamped to [0, tiles_x] and [0, tiles_y], int64 (no
    tensor made from host values: that would be a copy, which a graph cannot record)."""
    x = tiles[..., 0].clamp(min=0, max=grid.tiles_x)
    y = tiles[..., 1].clamp(min=0, max=grid.tiles_y)
    return torch.stack([x, y], -1).long()


def intersect_tiles(
    means2d: torch.Tensor,
    radii: torch.Tensor,
    depths: torch.Tensor,
    grid: TileGrid,
    capacity: int,
    kernel: bool = True,
) -> TileIntersections:
    """The sorted (tile, depth) intersections of `grid.images` images at `capacity` entries.

    means2d [I, N, 2], radii [I, N, 2] int32, depths [I, N] metres (camera z). No host read:
    every size is `capacity` or the inputs'. On CUDA our kernel builds it (`intersect_kernel`,
    unless `kernel` is False); the tensor version costs O(capacity log(I N)) for the
    entry-to-Gaussian search and one sort of `capacity` 64-bit keys (gsplat sorts the true count).
    """
    images, n = depths.shape
    first, end = tile_ranges(means2d, radii, grid)
    span = (end - first).reshape(-1, 2)  # [I N, 2] tiles across, down
    counts = span[:, 0] * span[:, 1]  # [I N]
    ends = torch.cumsum(counts, 0)  # [I N] exclusive end of each Gaussian's entries
    count = ends[-1] if ends.numel() else torch.zeros((), dtype=torch.long, device=depths.device)
    module = intersect_kernel(depths.device) if kernel and depths.is_cuda else None
    if module is not None:
        keys, ids = module.intersect_tiles_fixed(
            means2d.detach().float().contiguous(), radii.int().contiguous(), depths.detach().float().contiguous(),
            ends, grid.tile_size, grid.tiles_x, grid.tiles_y, grid.tile_bits, grid.image_bits, capacity,
            grid.padding_key,
        )  # fmt: skip
        return TileIntersections(keys, ids, count)
    entry = torch.arange(capacity, device=depths.device)
    owner = torch.searchsorted(ends, entry, right=True).clamp(max=images * n - 1)  # [capacity] flat image*N+gaussian
    local = entry - (ends[owner] - counts[owner])
    across = span[owner, 0].clamp(min=1)
    first_flat = first.reshape(-1, 2)
    tile_x = first_flat[owner, 0] + local % across
    tile_y = first_flat[owner, 1] + local // across
    image = torch.div(owner, n, rounding_mode="floor")
    depth_bits = (
        depths.detach().float().reshape(-1).view(torch.int32).long()[owner] & 0xFFFFFFFF
    )  # float32's, as gsplat's
    keys = (image << (32 + grid.tile_bits)) | ((tile_y * grid.tiles_x + tile_x) << 32) | depth_bits
    padded = entry >= count
    keys = torch.where(padded, torch.full_like(keys, grid.padding_key), keys)
    ids = torch.where(padded, torch.zeros_like(owner), owner)
    keys, order = torch.sort(keys, stable=True)
    return TileIntersections(keys, ids[order].int(), count)


def phantom_tile_mask(grid: TileGrid, device: torch.device) -> torch.Tensor:
    """[I, tiles_y + 1, tiles_x] bool: every tile drawn but the phantom row, where padding lands."""
    mask = torch.ones(grid.images, grid.tiles_y + 1, grid.tiles_x, dtype=torch.bool, device=device)
    mask[:, -1] = False
    return mask
