"""Keyframes: what they hold, the window mapped with a frame (by overlap with it), the one
dropped from a full store, and (`mapping.rate=keyframe`) which tracked frames become keyframes
by what they add (`KeyframeChooser`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from pipeline.config import Config, KeyframeConfig, keyframe_rate
from pipeline.frame import DeviceFrame
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
    return _landing_inside(depth, intrinsics, c2w, keyframe_c2w, pixels).float().mean(-1)


def _landing_inside(
    depth: torch.Tensor, intrinsics: torch.Tensor, c2w: torch.Tensor, keyframe_c2w: torch.Tensor, pixels: torch.Tensor
) -> torch.Tensor:
    """[K, P] whether each of the pixels (flat indices into depth [H, W]), back-projected from
    the camera at `c2w`, lands inside each keyframe's image (poses [K, 4, 4]) with positive depth."""
    height, width = depth.shape
    u, v = pixel_grid(height, width, depth.device)
    points = backproject(u.reshape(-1)[pixels], v.reshape(-1)[pixels], depth.reshape(-1)[pixels], intrinsics, c2w)
    uv, z = project(points[None], invert_pose(keyframe_c2w), intrinsics)
    return (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)


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


@dataclass(frozen=True)
class Novelty:
    """What a tracked frame adds beside the last keyframe."""

    overlap: float  # fraction of its valid-depth pixels (a grid of them) inside the last keyframe's view
    moved: float  # camera centres' distance over the frame's median valid depth (no valid depth: 0)


def grid_pixels(height: int, width: int, samples: int, device: torch.device) -> torch.Tensor:
    """Flat indices [P] of a regular grid of about `samples` pixels over an [H, W] image (every
    pixel when it has fewer): no random draw and no host read, unlike `sample_valid_pixels`."""
    stride = max(1, round(math.sqrt(height * width / samples)))
    rows = torch.arange(stride // 2, height, stride, device=device)
    cols = torch.arange(stride // 2, width, stride, device=device)
    return (rows[:, None] * width + cols[None, :]).reshape(-1)


def novelty(
    depth: torch.Tensor, intrinsics: torch.Tensor, c2w: torch.Tensor, keyframe_c2w: torch.Tensor, samples: int
) -> Novelty:
    """How much a frame (depth [H, W] metres, camera-to-world `c2w` [4, 4]) adds beside a keyframe
    at `keyframe_c2w` [4, 4], from a grid of about `samples` pixels (one host read). A frame
    without valid depth adds nothing: overlap 1, moved 0."""
    height, width = depth.shape
    pixels = grid_pixels(height, width, samples, depth.device)
    sampled = depth.reshape(-1)[pixels]
    valid = sampled > 0
    inside = _landing_inside(depth, intrinsics, c2w, keyframe_c2w[None], pixels)[0] & valid
    count = valid.sum()
    overlap = torch.where(count > 0, inside.sum() / count.clamp(min=1), torch.ones((), device=depth.device))
    median = torch.nanmedian(torch.where(valid, sampled, torch.full_like(sampled, math.nan)))
    distance = torch.linalg.norm(c2w[:3, 3] - keyframe_c2w[:3, 3].to(c2w))
    moved = torch.where(count > 0, distance / median.nan_to_num(1.0).clamp(min=1e-6), torch.zeros_like(distance))
    overlap_value, moved_value = torch.stack([overlap.float(), moved.float()]).tolist()
    return Novelty(overlap_value, moved_value)


class KeyframeChooser:
    """Which tracked frames become keyframes at `mapping.rate=keyframe`, on the tracking side and
    by what each adds, as MonoGS chooses them: a frame is a keyframe when the map covers little
    of it (`min_coverage`), when little of it lies in the last keyframe's view (`min_overlap`) or
    its camera has moved far from it (`max_translation` x its median depth); and at the latest
    `every` frames after the last keyframe, the first and a dataset's last frame always. The
    caller never offers a lost frame (it is never mapped), and says with `kept` which keyframe
    mapping took."""

    def __init__(self, config: KeyframeConfig) -> None:
        self.config = config
        self.last: KeyframePose | None = None  # the last keyframe kept, its pose as tracked

    def reason(
        self, frame: DeviceFrame, c2w: torch.Tensor, position: int, coverage: float | None, is_last: bool
    ) -> str:
        """Why the frame at `position` among the run's poses, tracked at camera-to-world `c2w`
        [4, 4], is a keyframe; empty when it is not. `coverage`: the fraction of its valid pixels
        the map covers, from a map version holding every keyframe kept so far (None: a version
        without the newest, which cannot say what the frame adds)."""
        config, last = self.config, self.last
        if last is None:
            return "the first frame"
        if is_last:
            return "the last frame"
        if position - last.position >= config.every:
            return f"{position - last.position} frames after the last keyframe (keyframes.every)"
        if coverage is not None and coverage < config.min_coverage:
            return f"the map covers {coverage:.0%} of it"
        added = novelty(frame.depth, frame.intrinsics, c2w, last.c2w, config.overlap_samples)
        if added.overlap < config.min_overlap:
            return f"{added.overlap:.0%} of it in the last keyframe's view"
        if added.moved > config.max_translation:
            return f"moved {added.moved:.2f} x its median depth"
        return ""

    def kept(self, keyframe: KeyframePose) -> None:
        """Mapping took this keyframe: the next frames are measured against it (a copy of its
        pose, never a tensor that changes under it: a row of a map version's stack)."""
        self.last = replace(keyframe, c2w=keyframe.c2w.clone())

    def resumed(self, keyframes: Sequence[KeyframePose]) -> None:
        """After a restore: the next keyframe is measured against the newest of `keyframes`."""
        if keyframes:
            self.kept(max(keyframes, key=lambda k: k.position))


def chooser_for(config: Config) -> KeyframeChooser | None:
    """The keyframe choice where only keyframes are mapped (`mapping.rate`, `keyframe_rate`);
    None: every frame is."""
    return KeyframeChooser(config.keyframes) if keyframe_rate(config.mapping.rate, config.slam.schedule) else None
