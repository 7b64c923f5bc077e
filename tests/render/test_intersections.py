"""Tile intersections at a fixed capacity against a direct construction of gsplat's list."""

from __future__ import annotations

import torch

from pipeline.render.intersections import TileGrid, intersect_tiles, phantom_tile_mask


def _projected(images: int, n: int, width: int, height: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    generator = torch.Generator().manual_seed(seed)
    means2d = torch.rand(images, n, 2, generator=generator) * torch.tensor([width + 40.0, height + 40.0]) - 20.0
    radii = torch.randint(0, 30, (images, n, 2), generator=generator, dtype=torch.int32)
    radii[torch.rand(images, n, generator=generator) < 0.2] = 0  # culled
    depths = torch.rand(images, n, generator=generator) * 4.0 + 0.1
    depths[0, :3] = depths[0, 3]  # equal depths: the stable order decides
    return means2d, radii, depths


def _direct(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, grid: TileGrid) -> list[tuple[int, int]]:
    """gsplat's `intersect_tile` kernel written as loops: (key, flat id) per entry, sorted by key
    (ties in creation order)."""
    entries = []
    images, n = depths.shape
    size = grid.tile_size
    for image in range(images):
        for g in range(n):
            rx, ry = (int(r) for r in radii[image, g])
            if rx <= 0 or ry <= 0:
                continue
            x, y = (float(v) / size for v in means2d[image, g])
            x0 = min(max(0, int(torch.floor(torch.tensor(x - rx / size)))), grid.tiles_x)
            y0 = min(max(0, int(torch.floor(torch.tensor(y - ry / size)))), grid.tiles_y)
            x1 = min(max(0, int(torch.ceil(torch.tensor(x + rx / size)))), grid.tiles_x)
            y1 = min(max(0, int(torch.ceil(torch.tensor(y + ry / size)))), grid.tiles_y)
            bits = int(depths[image, g].view(torch.int32)) & 0xFFFFFFFF
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    key = (image << (32 + grid.tile_bits)) | ((ty * grid.tiles_x + tx) << 32) | bits
                    entries.append((key, image * n + g))
    return sorted(entries, key=lambda entry: entry[0])  # Python's sort is stable


def test_the_entries_within_the_count_are_gsplats_sorted_list_and_the_rest_is_padding() -> None:
    means2d, radii, depths = _projected(images=2, n=40, width=70, height=50)
    grid = TileGrid(2, 70, 50)
    expected = _direct(means2d, radii, depths, grid)
    hits = intersect_tiles(means2d, radii, depths, grid, capacity=len(expected) + 37)
    count = int(hits.count)
    assert count == len(expected)
    assert list(zip(hits.keys[:count].tolist(), hits.flatten_ids[:count].tolist())) == expected
    assert (hits.keys[count:] == grid.padding_key).all() and (hits.flatten_ids[count:] == 0).all()
    assert not bool(hits.overflowed())


def test_padding_lands_in_the_phantom_row_which_the_mask_leaves_undrawn() -> None:
    grid = TileGrid(3, 70, 50)
    tile = (grid.padding_key >> 32) & ((1 << grid.tile_bits) - 1)
    image = grid.padding_key >> (32 + grid.tile_bits)
    assert image == 2 and tile // grid.tiles_x == grid.tiles_y  # the row below the image's tiles
    mask = phantom_tile_mask(grid, torch.device("cpu"))
    assert mask.shape == (3, grid.tiles_y + 1, grid.tiles_x)
    assert not mask[:, -1].any() and mask[:, :-1].all()


def test_a_capacity_below_the_count_is_reported_and_a_grown_one_gives_the_full_list() -> None:
    means2d, radii, depths = _projected(images=1, n=60, width=64, height=48, seed=3)
    grid = TileGrid(1, 64, 48)
    full = intersect_tiles(means2d, radii, depths, grid, capacity=4096)
    count = int(full.count)
    short = intersect_tiles(means2d, radii, depths, grid, capacity=count // 2)
    assert bool(short.overflowed()) and int(short.count) == count
    grown = intersect_tiles(means2d, radii, depths, grid, capacity=count + 1)
    assert torch.equal(grown.keys[:count], full.keys[:count])
    assert torch.equal(grown.flatten_ids[:count], full.flatten_ids[:count])


def test_no_gaussian_drawn_gives_only_padding() -> None:
    means2d, radii, depths = _projected(images=1, n=5, width=32, height=32)
    grid = TileGrid(1, 32, 32)
    hits = intersect_tiles(means2d, torch.zeros_like(radii), depths, grid, capacity=8)
    assert int(hits.count) == 0 and (hits.keys == grid.padding_key).all()
