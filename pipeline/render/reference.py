"""The pure-PyTorch renderer: gsplat's classic 3D path (EWA splatting) written plainly.

Same maths as gsplat 1.5: EWA projection with the eps2d dilation and the clamped Jacobian,
an opacity-aware 3.33-sigma box, per-tile depth order, and front-to-back compositing with
alpha = min(0.999, opacity x exp(-power)), alphas under 1/255 skipped and a pixel finished once
its transmittance would fall to 1e-4. Gradients come from autograd. It runs on any device and
is the oracle for the CUDA backend.

Its tiles are 8x8 where gsplat's are 16x16: a tile only decides which Gaussians its pixels
consider, and a pixel ignores a Gaussian whose box misses its tile, so the image is the same
except where a box was clamped at 3.33 sigma (opacities above 0.9988; measured: 7e-7 at most),
for about half the compositing work of 16x16 tiles at the test suite's 64x48.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pipeline.geometry import quat_to_rotmat
from pipeline.render.intersections import TileGrid, TileIntersections, intersect_tiles, tile_ranges
from pipeline.render.types import Camera, Gaussians, RenderOutput

TILE = 8
ALPHA_MAX = 0.999
CHUNK_ELEMENTS = 1 << 22  # tile x pixel x Gaussian elements per compositing chunk
REACH_MARGIN = 1e-4  # power units: `_contributors` keeps a superset of what `_alphas` keeps


@dataclass(frozen=True)
class Cutoffs:
    """gsplat's thresholds. They make the image a discontinuous function of the parameters
    (a pixel's alpha jumps from 0 to 1/255), which autograd ignores; `SMOOTH` removes them,
    so finite differences can check the gradient of the continuous part."""

    alpha_min: float = 1.0 / 255.0
    transmittance_min: float = 1e-4
    extent_sigmas: float = 3.33


GSPLAT = Cutoffs()
SMOOTH = Cutoffs(alpha_min=1e-30, transmittance_min=0.0, extent_sigmas=12.0)


def project(gaussians: Gaussians, camera: Camera, eps2d: float, cutoffs: Cutoffs = GSPLAT) -> dict[str, torch.Tensor]:
    """EWA projection of every Gaussian: 2D means, conics, depths, opacities and radii [N, 2]."""
    rot_w, t_w = camera.w2c[:3, :3], camera.w2c[:3, 3]
    means_c = gaussians.means @ rot_w.T + t_w
    m = quat_to_rotmat(gaussians.quats) * gaussians.scales()[:, None, :]
    cov_c = rot_w @ (m @ m.transpose(1, 2)) @ rot_w.T

    k = camera.intrinsics
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    x, y, z = means_c.unbind(-1)
    # Gaussians nearer than the near plane are culled below, but a depth of 0 among them would
    # still give infinities whose backward is NaN through the mask, for every mean and the pose
    # (a global adjustment on the CPU met one after 218 steps): they are divided by 1 instead.
    z = torch.where(z >= camera.near, z, torch.ones_like(z))
    depths = means_c[:, 2]
    lim_x_pos = (camera.width - cx) / fx + 0.3 * (0.5 * camera.width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * camera.width / fx)
    lim_y_pos = (camera.height - cy) / fy + 0.3 * (0.5 * camera.height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * camera.height / fy)
    tx = z * torch.clamp(x / z, -lim_x_neg, lim_x_pos)
    ty = z * torch.clamp(y / z, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * tx / z**2, zero, fy / z, -fy * ty / z**2], -1).reshape(-1, 2, 3)
    cov2d = jac @ cov_c @ jac.transpose(1, 2) + eps2d * torch.eye(2, dtype=z.dtype, device=z.device)
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    safe_det = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([cov2d[:, 1, 1], -cov2d[:, 0, 1], cov2d[:, 0, 0]], -1) / safe_det[:, None]
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    opacities = torch.sigmoid(gaussians.opacity_logits)

    with torch.no_grad():
        alpha_min = cutoffs.alpha_min
        extent = torch.clamp(
            torch.sqrt(2.0 * torch.log(opacities.clamp(min=alpha_min) / alpha_min)), max=cutoffs.extent_sigmas
        )
        var = torch.stack([cov2d[:, 0, 0], cov2d[:, 1, 1]], -1).clamp(min=0)
        radii = torch.ceil(extent[:, None] * torch.sqrt(var))
        valid = (depths >= camera.near) & (depths <= camera.far) & (det > 0) & (opacities >= alpha_min)
        valid &= (radii > 0).any(-1)
        valid &= (means2d[:, 0] + radii[:, 0] > 0) & (means2d[:, 0] - radii[:, 0] < camera.width)
        valid &= (means2d[:, 1] + radii[:, 1] > 0) & (means2d[:, 1] - radii[:, 1] < camera.height)
        radii = torch.where(valid[:, None], radii, torch.zeros_like(radii)).to(torch.int32)
    return {"means2d": means2d, "conics": conics, "depths": depths, "opacities": opacities, "radii": radii}


def exact_capacity(means2d: torch.Tensor, radii: torch.Tensor, grid: TileGrid) -> int:
    """The number of tile intersections (a host read): the capacity that loses nothing."""
    first, end = tile_ranges(means2d, radii, grid)
    span = end - first
    return max(int((span[..., 0] * span[..., 1]).sum()), 1)


@torch.no_grad()
def tile_lists(hits: TileIntersections, grid: TileGrid, image: int, n: int) -> torch.Tensor:
    """One image's per-tile Gaussian ids in depth order, from the sorted intersections of all
    images (entries past the capacity are lost, as gsplat's rasteriser would lose them):
    [tiles, K] int64, padded with -1."""
    kept = min(int(hits.count), hits.capacity)
    keys, ids = hits.keys[:kept], hits.flatten_ids[:kept].long()
    mine = (keys >> (32 + grid.tile_bits)) == image
    tile = (keys[mine] >> 32) & ((1 << grid.tile_bits) - 1)
    gid = ids[mine] - image * n
    n_tiles = grid.tiles_x * grid.tiles_y
    per_tile = torch.bincount(tile, minlength=n_tiles)
    width_k = int(per_tile.max()) if len(tile) else 0
    slot = torch.arange(len(tile), device=tile.device) - (torch.cumsum(per_tile, 0) - per_tile)[tile]
    lists = torch.full((n_tiles, max(width_k, 1)), -1, dtype=torch.long, device=keys.device)
    lists[tile, slot] = gid
    return lists


def _alphas(rows: torch.Tensor, pix: torch.Tensor, valid: torch.Tensor, alpha_min: float) -> torch.Tensor:
    """gsplat's per-pixel alpha of each listed Gaussian, 0 where it is skipped.

    rows [..., K, 6 + C] (mean, conic, opacity, features), pix [..., 2] pixel centres, valid
    [..., K] (a listed id, not padding) -> alpha [..., K].
    """
    mean, conic, opacity = rows[..., :2], rows[..., 2:5], rows[..., 5]
    dx = mean[..., 0] - pix[..., None, 0]
    dy = mean[..., 1] - pix[..., None, 1]
    power = 0.5 * (conic[..., 0] * dx * dx + conic[..., 2] * dy * dy) + conic[..., 1] * dx * dy
    alpha = torch.clamp(opacity * torch.exp(-power), max=ALPHA_MAX)
    used = valid & (power >= 0) & (alpha >= alpha_min)
    return torch.where(used, alpha, torch.zeros_like(alpha))


@torch.no_grad()
def _reach_table(proj: dict[str, torch.Tensor], alpha_min: float) -> torch.Tensor:
    """Per Gaussian, what `_contributors` tests: [6, N] rows mean x, mean y, conic a, b, c and
    the largest power at which its alpha still reaches alpha_min, log(opacity / alpha_min)."""
    reach = torch.log(proj["opacities"] / alpha_min) + REACH_MARGIN
    return torch.cat([proj["means2d"], proj["conics"], reach[:, None]], -1).T.contiguous()


@torch.no_grad()
def _contributors(reach_table: torch.Tensor, ids: torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
    """The ids, in depth order, of the Gaussians each pixel may not skip, padded with -1.

    reach_table [6, N] (`_reach_table`), ids [c, K] a chunk of tile lists, pix [c, P, 2] ->
    [c, P, K'] with K' the most any pixel keeps. A pixel skips most of its tile's list (alpha
    under 1/255: at 64x48 it keeps about one in seven), and a skipped Gaussian multiplies the
    transmittance by exactly 1, so compositing only the kept ones gives the same image for a
    fraction of the work. The test here, power <= log(opacity / alpha_min) with a margin, keeps
    a superset of what `_alphas` keeps (it decides exactly), without an exponential per pixel
    and Gaussian.
    """
    mean_x, mean_y, conic_a, conic_b, conic_c, reach = reach_table[:, ids.clamp(min=0)]  # each [c, K]
    dx = mean_x[:, None, :] - pix[..., 0, None]  # [c, P, K]
    dy = mean_y[:, None, :] - pix[..., 1, None]
    power = 0.5 * (conic_a[:, None, :] * dx * dx + conic_c[:, None, :] * dy * dy) + conic_b[:, None, :] * dx * dy
    used = power <= torch.where(ids >= 0, reach, -1.0)[:, None, :]
    counts = used.sum(-1).flatten()  # per pixel
    chunk, pixel, listed = used.nonzero(as_tuple=True)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(chunk), device=ids.device) - first[chunk * used.shape[1] + pixel]
    kept = torch.full((*used.shape[:2], max(int(counts.max()), 1)), -1, dtype=ids.dtype, device=ids.device)
    kept[chunk, pixel, slot] = ids[chunk, listed]
    return kept


def composite(
    proj: dict[str, torch.Tensor],
    features: torch.Tensor,
    lists: torch.Tensor,
    width: int,
    height: int,
    cutoffs: Cutoffs = GSPLAT,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Front-to-back alpha compositing per tile -> (features [H, W, C], alpha [H, W])."""
    device = features.device
    tiles_x = math.ceil(width / TILE)
    n_tiles, k = lists.shape
    local = torch.arange(TILE * TILE, device=device)
    offsets = torch.stack([local % TILE, local // TILE], -1).to(features.dtype) + 0.5  # pixel centres
    chunk = max(1, CHUNK_ELEMENTS // (TILE * TILE * k))
    # One row per Gaussian, gathered with index_select: its backward (index_add) sums in a fixed
    # order, where indexing's (index_put with accumulate) adds in parallel, in any order, once it
    # exceeds 32k elements, which makes two identical runs differ in the last bit.
    table = torch.cat([proj["means2d"], proj["conics"], proj["opacities"][:, None], features], -1)
    reach_table = _reach_table(proj, cutoffs.alpha_min)
    out_f, out_a = [], []
    for start in range(0, n_tiles, chunk):
        ids = lists[start : start + chunk]  # [c, K]
        tile_idx = torch.arange(start, start + len(ids), device=device)
        origin = torch.stack([tile_idx % tiles_x, tile_idx // tiles_x], -1).to(features.dtype) * TILE
        pix = origin[:, None, :] + offsets[None]  # [c, P, 2]
        kept = _contributors(reach_table, ids, pix)  # [c, P, K']
        rows = table.index_select(0, kept.clamp(min=0).reshape(-1)).view(*kept.shape, -1)  # [c, P, K', D]
        alpha = _alphas(rows, pix, kept >= 0, cutoffs.alpha_min)
        transmit = torch.cumprod(1 - alpha, dim=-1)  # after each Gaussian
        alpha = torch.where(
            transmit > cutoffs.transmittance_min, alpha, torch.zeros_like(alpha)
        )  # stop rule, exclusive
        before = torch.cat([torch.ones_like(transmit[..., :1]), transmit[..., :-1]], -1)
        weight = alpha * before  # [c, P, K']
        out_f.append((weight[..., None] * rows[..., 6:]).sum(-2))  # [c, P, C]
        out_a.append(weight.sum(-1))
    feat = torch.cat(out_f).reshape(-1, TILE, TILE, features.shape[-1])
    acc = torch.cat(out_a).reshape(-1, TILE, TILE)
    tiles_y = n_tiles // tiles_x
    feat = (
        feat.reshape(tiles_y, tiles_x, TILE, TILE, -1)
        .permute(0, 2, 1, 3, 4)
        .reshape(tiles_y * TILE, tiles_x * TILE, -1)
    )
    acc = acc.reshape(tiles_y, tiles_x, TILE, TILE).permute(0, 2, 1, 3).reshape(tiles_y * TILE, tiles_x * TILE)
    return feat[:height, :width], acc[:height, :width]


def render_reference_views(
    gaussians: Gaussians,
    cameras: list[Camera],
    capacity: int | None = None,
    eps2d: float = 0.3,
    cutoffs: Cutoffs = GSPLAT,
) -> tuple[list[RenderOutput], TileIntersections]:
    """Cameras of one size, their tile intersections at `capacity` entries shared by all (None:
    exactly as many as there are), as gsplat's fixed-capacity render takes them; what a smaller
    capacity loses is lost from the images."""
    first = cameras[0]
    projs = [project(gaussians, camera, eps2d, cutoffs) for camera in cameras]
    means2d, radii, depths = (torch.stack([p[key] for p in projs]) for key in ("means2d", "radii", "depths"))
    grid = TileGrid(len(cameras), first.width, first.height, TILE)
    hits = intersect_tiles(means2d, radii, depths, grid, capacity or exact_capacity(means2d, radii, grid))
    outputs = []
    for image, proj in enumerate(projs):
        lists = tile_lists(hits, grid, image, len(gaussians))
        features = torch.cat([gaussians.colors, proj["depths"][:, None]], -1)
        feat, alpha = composite(proj, features, lists, first.width, first.height, cutoffs)
        depth = feat[..., 3] / alpha.clamp(min=1e-10)
        radii_max = proj["radii"].amax(-1)
        outputs.append(RenderOutput(feat[..., :3], depth, alpha, radii_max, radii_max > 0))
    return outputs, hits


def render_reference(
    gaussians: Gaussians, camera: Camera, eps2d: float = 0.3, cutoffs: Cutoffs = GSPLAT
) -> RenderOutput:
    return render_reference_views(gaussians, [camera], None, eps2d, cutoffs)[0][0]
