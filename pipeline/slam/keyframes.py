"""Keyframes and their selection by overlap with the current frame."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.geometry import backproject, invert_pose, pixel_grid, project


@dataclass(frozen=True)
class KeyframePose:
    """A keyframe as tracking sees it in a map version: where it is, not its images."""

    index: int  # the frame's index
    c2w: torch.Tensor  # [4, 4] camera-to-world
    position: int  # the frame's position among the run's poses


@dataclass
class Keyframe:
    """A frame kept for mapping. Colour is stored as 8-bit (what the camera gave): a quarter of
    the memory of float32, which matters at hundreds of keyframes."""

    index: int
    color_u8: torch.Tensor  # [H, W, 3] uint8
    depth: torch.Tensor  # [H, W] metres
    c2w: torch.Tensor  # [4, 4] estimated camera-to-world
    position: int = -1  # the frame's position among the run's poses; -1: its index (datasets: the same)

    @staticmethod
    def of(index: int, color: torch.Tensor, depth: torch.Tensor, c2w: torch.Tensor, position: int = -1) -> Keyframe:
        """From a float colour image [H, W, 3] in [0, 1]."""
        return Keyframe(index, (color * 255).round_().to(torch.uint8), depth, c2w, position)

    @property
    def pose(self) -> KeyframePose:
        return KeyframePose(self.index, self.c2w, self.position if self.position >= 0 else self.index)

    @property
    def color(self) -> torch.Tensor:
        """[H, W, 3] float32 in [0, 1]."""
        return self.color_u8.float() / 255.0


def sample_valid_pixels(depth: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """Flat indices [count] of valid-depth pixels drawn uniformly with replacement (as SplaTAM);
    empty when no pixel is valid."""
    valid = torch.nonzero(depth.reshape(-1) > 0)[:, 0]
    if len(valid) == 0:
        return valid
    pick = torch.randint(len(valid), (count,), generator=generator)
    if valid.is_cuda:  # from pinned memory the copy is queued; from pageable memory it would wait for the GPU
        pick = pick.pin_memory()
    return valid[pick.to(valid.device, non_blocking=True)]


def overlap_fractions(
    depth: torch.Tensor,
    intrinsics: torch.Tensor,
    c2w: torch.Tensor,
    keyframe_c2w: torch.Tensor,
    pixels: torch.Tensor,
) -> torch.Tensor:
    """Fraction of the sampled pixels (flat indices into depth [H, W]) that land inside each
    keyframe's image with positive depth: [K] for keyframe poses [K, 4, 4] (camera-to-world)."""
    height, width = depth.shape
    u, v = pixel_grid(height, width, depth.device)
    points = backproject(u.reshape(-1)[pixels], v.reshape(-1)[pixels], depth.reshape(-1)[pixels], intrinsics, c2w)
    uv, z = project(points[None], invert_pose(keyframe_c2w), intrinsics)
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)
    return inside.float().mean(-1)


def select_window(
    keyframes: list[Keyframe],
    depth: torch.Tensor,
    intrinsics: torch.Tensor,
    c2w: torch.Tensor,
    window: int,
    samples: int,
    generator: torch.Generator,
) -> list[int]:
    """Keyframe positions for mapping: overlapping ones in random order (at most window - 2),
    plus the newest keyframe. The caller adds the current frame."""
    if not keyframes:
        return []
    older = keyframes[:-1]
    chosen: list[int] = []
    if older:
        pixels = sample_valid_pixels(depth, samples, generator)
        poses = torch.stack([kf.c2w for kf in older])
        overlapping = torch.nonzero(overlap_fractions(depth, intrinsics, c2w, poses, pixels) > 0)[:, 0].cpu()
        order = torch.randperm(len(overlapping), generator=generator)
        chosen = overlapping[order][: max(window - 2, 0)].tolist()
    return chosen + [len(keyframes) - 1]


ROTATION_WEIGHT_M = 0.5  # metres of viewpoint change that count as much as one radian of rotation


def most_redundant(c2w: torch.Tensor, protected_newest: int) -> int:
    """The position of the keyframe to drop when the store is full: of poses [K, 4, 4]
    (camera-to-world, oldest first), the one closest to its next newer keyframe (camera-centre
    distance plus ROTATION_WEIGHT_M per radian between their viewing directions). The first and
    the newest `protected_newest` are never chosen, so the start and the mapping window stay."""
    count = c2w.shape[0]
    candidates = range(1, count - protected_newest)
    if not candidates:
        raise ValueError(f"no keyframe of {count} may go with the newest {protected_newest} protected")
    poses = c2w.detach().double().cpu()  # [K, 4, 4]: small, read once
    step = torch.linalg.norm(poses[1:, :3, 3] - poses[:-1, :3, 3], dim=-1)
    cosine = (poses[1:, :3, 2] * poses[:-1, :3, 2]).sum(-1).clamp(-1.0, 1.0)
    distance = step + ROTATION_WEIGHT_M * torch.arccos(cosine)  # [K - 1]: keyframe i to i + 1
    return min(candidates, key=lambda i: float(distance[i]))


def relocalisation_picks(count: int, candidates: int, attempt: int) -> list[int]:
    """Positions (oldest first) of at most `candidates` of `count` keyframes whose poses the
    `attempt`-th lost frame in a row (0 first) is tracked again from: every `stride`-th keyframe
    (stride = ceil(count / candidates)) from position `attempt mod stride`. Each attempt spreads
    over the whole store, the first includes the oldest keyframe (where the map began), and
    `stride` lost frames in a row try every keyframe once."""
    if count == 0 or candidates == 0:
        return []
    stride = -(-count // candidates)
    return list(range(attempt % stride, count, stride))
