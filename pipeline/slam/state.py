"""What a checkpoint holds: a host copy of everything SLAM carries from frame to frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe


@dataclass
class Checkpoint:
    """Everything needed to continue a run, on the host: a copy SLAM's later updates do not
    touch (safe to write from another thread while SLAM goes on)."""

    gaussians: Gaussians
    keyframes: list[Keyframe]
    poses: torch.Tensor  # [F, 4, 4] estimated camera-to-world per frame
    scene_radius: float  # metres
    loss_history: list[float]
    last_prior: torch.Tensor | None  # [4, 4] camera-to-world
    rng_state: tuple[Any, ...]  # random.Random.getstate(): mapping's view picks
    generator_state: torch.Tensor  # torch.Generator.get_state() (uint8): keyframe sampling
    lost_frames: list[int] = field(default_factory=list)  # positions in `poses` of the frames judged lost
    relocalised_frames: list[int] = field(default_factory=list)  # and of those relocalised

    @property
    def frames_done(self) -> int:
        return int(self.poses.shape[0])
