"""Loop candidates: the old keyframes the newest one may see again, by where the current
estimates put the cameras (centre distance, viewing angle, and the share of the newest
keyframe's pixels that land in their images, `overlap_fractions`), ranked by a global
descriptor: a small, blurred, zero-mean thumbnail of intensity, compared by correlation, as
PTAM's relocaliser compares small blurry images.

The estimates drift most on the loops that most need closing: on a real loop round a cabinet
they put the end 2 m and 44 degrees from the start, which the truth puts 0.34 m and 6 degrees
away (bench/NOTES.md). So a keyframe that looks very like the newest one (`appearance_similarity`)
is a candidate beyond the estimates' reach too, as far as they may have drifted since it
(`drift_fraction` of the path travelled); its verification does not start from the estimates
(`detection.start_poses`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from pipeline.config import LoopConfig
from pipeline.slam.keyframes import Keyframe, overlap_fractions
from pipeline.slam.tracking.pyramid import intensity

THUMBNAIL = (12, 16)  # rows, columns of the descriptor's thumbnails
BLUR_SIGMA = 2.0  # thumbnail pixels: a small shift of the view changes the thumbnail little


@dataclass(frozen=True)
class LoopCandidate:
    """An old keyframe near the current one, by the current estimates."""

    position: int  # in the keyframes passed (the pose graph's node)
    similarity: float  # descriptor correlation, -1 to 1
    distance_m: float  # between the camera centres
    angle_deg: float  # between the viewing directions
    overlap: float  # fraction of the current keyframe's sampled pixels inside its image
    by_appearance: bool = False  # beyond the estimates' reach: a candidate by its look (and the drift allowed) alone


def blurred_thumbnail(image: torch.Tensor) -> torch.Tensor:
    """[H, W] -> [THUMBNAIL] by area averaging, then a Gaussian blur of BLUR_SIGMA."""
    small = F.adaptive_avg_pool2d(image[None, None], THUMBNAIL)
    radius = math.ceil(2 * BLUR_SIGMA)
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-0.5 * (offsets / BLUR_SIGMA) ** 2)
    kernel = kernel / kernel.sum()
    small = F.conv2d(F.pad(small, [radius, radius, 0, 0], mode="replicate"), kernel.view(1, 1, 1, -1))
    small = F.conv2d(F.pad(small, [0, 0, radius, radius], mode="replicate"), kernel.view(1, 1, -1, 1))
    return small[0, 0]


def standardised(values: torch.Tensor) -> torch.Tensor:
    """Flattened, zero mean and unit norm (zeros when constant)."""
    flat = values.reshape(-1)
    flat = flat - flat.mean()
    return flat / flat.norm().clamp(min=1e-12)


def descriptor(color: torch.Tensor) -> torch.Tensor:
    """A keyframe's global descriptor [12 x 16] from its colour [H, W, 3] in [0, 1]: the
    intensity's blurred thumbnail, zero mean and norm 1, so that the dot product of two is
    their correlation (a change of exposure does not count). Measured against ORB words and
    against adding inverse depth on generated loops (bench/loop_descriptors.py): as good at
    ranking the views near a keyframe, and needs no vocabulary."""
    return standardised(blurred_thumbnail(intensity(color)))


def _viewing_angles_deg(c2w: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Degrees between the optical axis of `c2w` [4, 4] and those of `poses` [K, 4, 4]."""
    cosine = (poses[:, :3, 2] * c2w[:3, 2]).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cosine))


def loop_candidates(
    keyframes: Sequence[Keyframe],
    descriptors: torch.Tensor,
    intrinsics: torch.Tensor,
    pixels: torch.Tensor,
    config: LoopConfig,
    lost: bool = False,
) -> list[LoopCandidate]:
    """The old keyframes the newest of `keyframes` (oldest first, current estimates) may see
    again, most similar first, at most `max_candidates`: at least `min_keyframes_back` older,
    camera centre within `radius_m`, viewing direction within `max_angle_deg`, at least
    `min_overlap` of the current keyframe's sampled `pixels` (flat indices into its depth) in
    their images, descriptor similarity at least `min_similarity`; or, beyond that reach, a
    similarity of at least `appearance_similarity` and a centre within `radius_m` plus
    `drift_fraction` of the path the estimates travelled since; or, where the newest is a frame
    tracking `lost` (its pose is no measurement: on the cabinet's revisit it sat 2.5 m from the
    first keyframe, the reach 2.3 m), that similarity alone, anywhere, as a relocaliser searches
    its whole keyframe database. `descriptors` [K, D], one per keyframe (`descriptor`)."""
    old = len(keyframes) - config.min_keyframes_back
    if old <= 0:
        return []
    current = keyframes[-1]
    every = torch.stack([keyframe.c2w for keyframe in keyframes]).double()
    poses, c2w = every[:old], every[-1]
    distance = (poses[:, :3, 3] - c2w[:3, 3]).norm(dim=-1)
    angle = _viewing_angles_deg(c2w, poses)
    overlap = overlap_fractions(current.depth, intrinsics, current.c2w, poses.to(current.c2w), pixels).double()
    similarity = (descriptors[:old] @ descriptors[-1]).double()
    near = (distance <= config.radius_m) & (angle <= config.max_angle_deg) & (overlap >= config.min_overlap)
    reach = config.radius_m + config.drift_fraction * travelled_m(every)[:old]
    far = ~near & ((distance <= reach) | lost) & (similarity >= config.appearance_similarity)
    passing = torch.nonzero((near & (similarity >= config.min_similarity)) | far)[:, 0]
    ranked = passing[torch.argsort(similarity[passing], descending=True)][: config.max_candidates]
    stats = torch.stack([similarity, distance, angle, overlap, far.double()]).cpu()  # one read of [5, K]
    found = []
    for k in ranked.tolist():
        similar, distant, angled, overlapping, by_appearance = (float(x) for x in stats[:, k])
        found.append(LoopCandidate(k, similar, distant, angled, overlapping, bool(by_appearance)))
    return found


def travelled_m(poses: torch.Tensor) -> torch.Tensor:
    """[K]: the path from each of `poses` [K, 4, 4] (camera-to-world, in order) to the last, in
    metres: the sum of the steps between their camera centres."""
    steps = (poses[1:, :3, 3] - poses[:-1, :3, 3]).norm(dim=-1)
    return torch.cat([steps.flip(0).cumsum(0).flip(0), steps.new_zeros(1)])
