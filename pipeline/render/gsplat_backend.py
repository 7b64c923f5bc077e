"""The CUDA renderer: one gsplat rasterisation per call gives colour, depth and silhouette.

Imported only when CUDA is available: importing gsplat's CUDA backend on a machine with nvcc
but no GPU starts a long JIT compile that fails.

Choices (measured in bench/results/rendering.md):
- `render_mode="RGB+ED"`: depth rides along as a fourth colour channel, normalised by alpha,
  so one pass returns all three images; the camera-pose gradient flows through `viewmats`.
- `rasterize_mode="classic"`: SplaTAM composites without the antialiasing compensation, and
  the reference backend reproduces classic exactly.
- `packed`: configurable (RenderConfig.packed); unpacked is the default because on the H100 it
  was faster at SLAM map sizes (see the results file).
- `eps2d=0.3`: gsplat's default 2D dilation, which keeps sub-pixel Gaussians at least ~0.5 px wide.
"""

from __future__ import annotations

from typing import Any

import gsplat
import torch

from pipeline.render.intersections import TileGrid, TileIntersections, intersect_tiles, phantom_tile_mask
from pipeline.render.types import Camera, Gaussians, RenderOutput


def _output(colors: torch.Tensor, alphas: torch.Tensor, radii: torch.Tensor, n: int) -> RenderOutput:
    radii = radii.reshape(n, -1).amax(-1)
    return RenderOutput(colors[0, ..., :3], colors[0, ..., 3], alphas[0, ..., 0], radii, radii > 0)


def _radii_per_gaussian(meta: dict, n: int, packed: bool) -> torch.Tensor:
    if not packed:
        return meta["radii"]
    full = torch.zeros((n, 2), dtype=torch.int32, device=meta["radii"].device)
    full[meta["gaussian_ids"]] = meta["radii"].reshape(-1, 2) if meta["radii"].dim() > 1 else meta["radii"][:, None]
    return full


def _arguments(gaussians: Gaussians, camera: Camera, eps2d: float, packed: bool) -> dict[str, Any]:
    """What both gsplat rasterisers take, one camera, colour plus expected depth."""
    return {
        "means": gaussians.means,
        "quats": gaussians.quats,
        "scales": gaussians.scales(),
        "opacities": torch.sigmoid(gaussians.opacity_logits),
        "viewmats": camera.w2c[None],
        "Ks": camera.intrinsics[None],
        "width": camera.width,
        "height": camera.height,
        "near_plane": camera.near,
        "far_plane": camera.far,
        "eps2d": eps2d,
        "packed": packed,
        "render_mode": "RGB+ED",
    }


def render_gsplat_3d(gaussians: Gaussians, camera: Camera, eps2d: float = 0.3, packed: bool = False) -> RenderOutput:
    colors, alphas, meta = gsplat.rasterization(
        colors=gaussians.colors, rasterize_mode="classic", **_arguments(gaussians, camera, eps2d, packed)
    )
    radii = _radii_per_gaussian(meta, len(gaussians), packed)
    return _output(colors, alphas, radii, len(gaussians))


def render_gsplat_3d_views(gaussians: Gaussians, cameras: list[Camera], eps2d: float = 0.3) -> list[RenderOutput]:
    """Several cameras of one size in one unpacked rasterisation (gsplat's batched cameras)."""
    arguments = _arguments(gaussians, cameras[0], eps2d, packed=False)
    arguments["viewmats"] = torch.stack([camera.w2c for camera in cameras])
    arguments["Ks"] = torch.stack([camera.intrinsics for camera in cameras])
    colors, alphas, meta = gsplat.rasterization(colors=gaussians.colors, rasterize_mode="classic", **arguments)
    n = len(gaussians)
    return [_output(colors[c : c + 1], alphas[c : c + 1], meta["radii"][c], n) for c in range(len(cameras))]


def render_gsplat_2d(gaussians: Gaussians, camera: Camera, eps2d: float = 0.3, packed: bool = False) -> RenderOutput:
    """2D Gaussian surfels (2DGS): the third scale axis is ignored by the rasteriser.

    Colours go in per camera ([1, N, 3]): gsplat 1.5.3's 2DGS path cannot append the depth
    channel to unbatched [N, 3] colours.
    """
    colors, alphas, *_, meta = gsplat.rasterization_2dgs(
        colors=gaussians.colors[None], **_arguments(gaussians, camera, eps2d, packed)
    )
    radii = _radii_per_gaussian(meta, len(gaussians), packed)
    return _output(colors, alphas, radii, len(gaussians))


def render_gsplat_3d_capacity(
    gaussians: Gaussians, cameras: list[Camera], capacity: int, eps2d: float = 0.3
) -> tuple[list[RenderOutput], TileIntersections]:
    """`render_gsplat_3d_views` with no host read: the tile intersections at a fixed `capacity`
    (`intersections.intersect_tiles`), so the call can be recorded in a CUDA graph.

    The same kernels as `gsplat.rasterization` (classic, unpacked, "RGB+ED") on the same
    inputs, so the images equal its images while the intersections fit; the returned
    intersections say whether they did (`overflowed()`, read when convenient)."""
    from gsplat.cuda._wrapper import fully_fused_projection, isect_offset_encode, rasterize_to_pixels

    first = cameras[0]
    opacities = torch.sigmoid(gaussians.opacity_logits)
    radii, means2d, depths, conics, _ = fully_fused_projection(
        gaussians.means,
        None,
        gaussians.quats,
        gaussians.scales(),
        torch.stack([camera.w2c for camera in cameras]),
        torch.stack([camera.intrinsics for camera in cameras]),
        first.width,
        first.height,
        eps2d=eps2d,
        near_plane=first.near,
        far_plane=first.far,
        opacities=opacities,
    )
    images, n = depths.shape
    grid = TileGrid(images, first.width, first.height)
    hits = intersect_tiles(means2d, radii, depths, grid, capacity)
    offsets = isect_offset_encode(hits.keys, images, grid.tiles_x, grid.tiles_y + 1)
    features = torch.cat([gaussians.colors.expand(images, n, 3), depths[..., None]], -1)
    colors, alphas = rasterize_to_pixels(
        means2d,
        conics,
        features,
        opacities.expand(images, n),
        first.width,
        first.height,
        grid.tile_size,
        offsets.reshape(images, grid.tiles_y + 1, grid.tiles_x),
        hits.flatten_ids,
        masks=phantom_tile_mask(grid, depths.device),
    )
    depth = colors[..., 3:] / alphas.clamp(min=1e-10)
    outputs = [
        _output(torch.cat([colors[c : c + 1, ..., :3], depth[c : c + 1]], -1), alphas[c : c + 1], radii[c], n)
        for c in range(images)
    ]
    return outputs, hits
