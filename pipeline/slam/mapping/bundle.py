"""Local bundle adjustment: at each keyframe kept, the poses of the keyframes that see most of
what it sees are optimised jointly with the map (the pose gradient through each view matrix, as
refinement does, `window.optimise_window`), until a round of renders moves no pose any more
(`mapping.adjust_converged`) or `mapping.adjust_iters` renders are spent. The oldest keyframe of
the window stays where it is: it fixes the window's frame (the gauge), so the adjustment cannot
slide the whole window and the map with it. Frames follow their keyframes through the anchors
(`TrackingFrontend.poses_with`)."""

from __future__ import annotations

import random

import torch

from pipeline.render import Gaussians
from pipeline.slam.keyframes import Keyframe, overlap_fractions, sample_valid_pixels
from pipeline.slam.mapping.window import MapSettings, WindowPlan, WindowResult, optimise_window


def covisible(
    keyframes: list[Keyframe], count: int, intrinsics: torch.Tensor, samples: int, generator: torch.Generator
) -> list[int]:
    """Positions in `keyframes` (the store, oldest first) of the newest and the at most
    `count - 1` others that see the largest share of its `samples` sampled valid-depth pixels
    (`overlap_fractions`, none that sees none), oldest first."""
    newest = len(keyframes) - 1
    if newest == 0 or count < 2:
        return [newest]
    current = keyframes[-1]
    pixels = sample_valid_pixels(current.depth, samples, generator)
    poses = torch.stack([keyframe.c2w for keyframe in keyframes[:-1]])
    overlap = overlap_fractions(current.depth, intrinsics, current.c2w, poses, pixels).cpu()  # [K - 1]: one read
    ranked = torch.argsort(overlap, descending=True, stable=True)[: count - 1]
    return sorted(int(k) for k in ranked if overlap[k] > 0) + [newest]


def adjust(
    gaussians: Gaussians,
    views: list[Keyframe],
    intrinsics: torch.Tensor,
    scene_radius: float,
    rng: random.Random,
    settings: MapSettings,
) -> WindowResult:
    """The map and the poses of `views` (oldest first; the first stays) optimised together."""
    config = settings.mapping
    plan = WindowPlan(
        config.adjust_iters,
        pose_lr=config.adjust_pose_lr,
        fixed=frozenset({0}),
        converged=config.adjust_converged,
    )
    return optimise_window(gaussians, views, intrinsics, scene_radius, rng, settings, plan)
